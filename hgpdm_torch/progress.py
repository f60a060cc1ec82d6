"""Progress bars: tqdm's notebook widget where Jupyter can draw it, its text bar elsewhere.

Inside a Jupyter kernel ``tqdm.auto`` picks the widget bar and, where ipywidgets is not
installed, warns at import (``TqdmWarning: IProgress not found``, with the path of tqdm on the
machine). Every module of the toolkit imports its bars from here instead: the widget bar only
where ipywidgets can be imported, the text bar (on stderr) otherwise, so the toolkit itself
never warns. (Pyro's MCMC logger imports ``tqdm.auto`` too, so a notebook without ipywidgets
still shows the warning once ``pyro.infer`` is imported: the ``test`` extra, which executes the
tutorials, installs ipywidgets.) The classes are tqdm's own.
"""

from __future__ import annotations

from importlib.util import find_spec

if find_spec("ipywidgets") is not None:
    from tqdm.auto import tqdm, trange
else:
    from tqdm.std import tqdm, trange

__all__ = ["tqdm", "trange"]
