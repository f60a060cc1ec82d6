"""Safe persistence of models: a versioned, checksummed file of a model's state and a small
configuration, an allow-list of classes, and loading into a model your own code built.

:meth:`GPDM.save <hgpdm_torch.models.GPDM.save>` writes, and :func:`load_model` reads, one file:

=========  ======  ===========================================================================
offset     bytes   content
=========  ======  ===========================================================================
0          16      :data:`MAGIC`, ``b"\\x89hgpdm-torch\\r\\n\\x1a\\n"``
16         4       format version, unsigned little-endian (:data:`FORMAT_VERSION`)
20         8       payload length P in bytes, unsigned little-endian
28         32      SHA-256 of bytes ``0 .. 28`` followed by the payload (everything but itself)
60         P       payload: ``torch.save`` of a dict (below)
=========  ======  ===========================================================================

The format-2 payload is ``{"format": 2, "class", "config", "data", "state_dict",
"user_arguments"}``:

* ``class``: the name the model's class is registered under (:func:`register_model`);
* ``config``: the constructor options that are plain values (``None``, bool, int, float, str,
  and lists and str-keyed dicts of them; JSON-able), ``"dtype"`` among them: the class's own
  :meth:`~hgpdm_torch.models.GPDM.config` plus the plain arguments a subclass's constructor
  was called with (recorded automatically, see :func:`register_model`);
* ``data``: the training data the constructor takes (``sequences``, ``intentions``);
* ``state_dict``: ``model.state_dict()``, every parameter and buffer (kernel hyperparameters,
  learned latent states, the parameters of custom kernels, priors and back-constraint maps);
* ``user_arguments``: ``{argument: type name}`` of the constructor arguments the model was built
  with that are objects, not plain values (a custom gpytorch kernel, priors, a back-constraint
  module, a subclass's object argument): a file cannot rebuild them.

:func:`load_model` rebuilds the model with the registered class's constructor from the data and
configuration, then loads the state into it. A file with ``user_arguments`` is loaded into a
model your code builds with those objects instead: ``load_model(path, model=MyModel(...))``
checks that the given model matches the file (class, dtype, the saved plain options) and loads
the state into it, strictly (every key, every shape). Format-1 files (release 1's layout, payload
``{"class", "config", "data", "state_dict", "dtype"}``) still load, the same way.

Loading checks, in this order, the magic bytes, the version (a newer version is refused before
anything else is read, as its layout may differ), the length, the checksum, the payload's
structure, the class name against the registry, and finally that the training data stored beside
the configuration equal those in the ``state_dict``. Every failure raises :class:`ModelFileError`
naming the file and what is wrong or missing.

The checksum detects corruption (a damaged disk, a cut-off copy), not deliberate tampering:
anyone can write a file with a matching hash. Safety against malicious files comes from two
other rules: the payload is read with ``torch.load(..., weights_only=True)`` (no pickled code),
and the class is looked up in an allow-list of registered model classes, never imported from a
module named by the file. :class:`GPDM`, :class:`HGPDM`, :class:`IDDM` and :class:`LinearIDDM`
are registered; a subclass of your own is registered with :func:`register_model`.

A :class:`LinearIDDM` keeps its training data outside its statistics, so it is rebuilt by
fitting it again with the saved choices (``LinearIDDM._from_saved``; a file asking for an evidence
or cross-validation search, or holding coefficients of a shape its data do not imply, is
refused before any fitting), and the saved statistics must agree with that fit before they are
taken (:meth:`LinearIDDM.load_state_dict`): for it, that is the data/state check of the last
step.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import io
import os
import secrets
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, TypeVar, overload

import numpy as np
import torch

__all__ = [
    "FORMAT_VERSION",
    "MAGIC",
    "ModelFileError",
    "SavedModel",
    "load_model",
    "register_model",
    "registered_models",
    "save_model",
]

#: First bytes of every model file (PNG-style: a non-ASCII byte, the name, CR LF, EOF, LF, so
#: that text-mode transfers and truncation to 7 bits are detected).
MAGIC = b"\x89hgpdm-torch\r\n\x1a\n"
#: The format version this release writes; it reads versions ``1 .. FORMAT_VERSION``.
FORMAT_VERSION = 2
_HEADER = struct.Struct("<IQ")  # version, payload length
_DIGEST_SIZE = hashlib.sha256().digest_size
_PREFIX_SIZE = len(MAGIC) + _HEADER.size + _DIGEST_SIZE
_PAYLOAD_KEYS = {
    1: frozenset({"class", "config", "data", "state_dict", "dtype"}),
    2: frozenset({"format", "class", "config", "data", "state_dict", "user_arguments"}),
}
_DTYPES = {
    "float16": torch.float16,
    "bfloat16": torch.bfloat16,
    "float32": torch.float32,
    "float64": torch.float64,
}


class ModelFileError(ValueError):
    """A file is not a model file this release can load: foreign, empty, truncated, corrupted,
    of an unknown format version, naming an unregistered class, inconsistent, needing arguments
    only your code can build (pass ``model=``), or not fitting the model given."""


# --------------------------------------------------------------------- constructor arguments
class _NotPlain(Exception):
    pass


def _plain(value: Any) -> Any:
    """A copy of ``value`` if it is a plain (JSON-able) value: ``None``, bool, int, float, str,
    and lists, tuples and str-keyed dicts of them (NumPy scalars become Python's); else raise
    :class:`_NotPlain`."""
    if isinstance(value, np.generic) and not isinstance(value, np.void):
        value = value.item()
    if value is None or type(value) in (bool, int, float, str):
        return value
    if type(value) in (list, tuple):
        return type(value)(_plain(v) for v in value)
    if type(value) is dict and all(type(k) is str for k in value):
        return {k: _plain(v) for k, v in value.items()}
    raise _NotPlain


def _is_plain(value: Any) -> bool:
    try:
        _plain(value)
    except _NotPlain:
        return False
    return True


@dataclass(frozen=True)
class _Unrecorded:
    """Stands for a constructor argument that is an object (its type name), not a value."""

    type_name: str


@functools.cache
def _class_arguments(cls: type) -> tuple[inspect.Signature | None, frozenset[str], frozenset[str]]:
    """``cls.__init__``'s signature, the argument names of the ``__init__`` of the hgpdm_torch
    classes it derives from, and the names to record: those of the other model classes in its
    MRO (a subclass's own arguments) and ``cls.object_arguments``."""
    try:
        signature = inspect.signature(cls.__init__)
    except (TypeError, ValueError):
        signature = None
    library: set[str] = set()
    own: set[str] = set()
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        if init is None or klass is SavedModel:
            continue
        try:
            params = list(inspect.signature(init).parameters.values())[1:]
        except (TypeError, ValueError):
            continue
        names = {p.name for p in params if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)}
        if klass.__module__.split(".")[0] == "hgpdm_torch":
            library.update(names)
        elif issubclass(klass, SavedModel):  # not torch's or gpytorch's Module
            own.update(names)
    objects = set(getattr(cls, "object_arguments", ()))
    return signature, frozenset(library), frozenset((own - library) | objects)


def _capture(cls: type, args: tuple, kwargs: dict) -> dict[str, Any] | None:
    """The arguments of a constructor call that :func:`save_model` may need: a subclass's own
    arguments and ``cls.object_arguments``, each a plain copy or an :class:`_Unrecorded`; ``None``
    where the call does not bind (the constructor then raises, or it is an unpickling)."""
    signature, _, wanted = _class_arguments(cls)
    if signature is None:
        return None
    try:
        bound = signature.bind(None, *args, **kwargs)
    except TypeError:
        return None
    bound.apply_defaults()
    given: dict[str, Any] = {}
    for param in list(signature.parameters.values())[1:]:
        value = bound.arguments.get(param.name)
        if param.kind is param.VAR_KEYWORD:
            given.update(value)
        elif param.kind is not param.VAR_POSITIONAL:
            given[param.name] = value
    recorded = {}
    for name in wanted & given.keys():
        try:
            recorded[name] = _plain(given[name])
        except _NotPlain:
            recorded[name] = _Unrecorded(type(given[name]).__qualname__)
    return recorded


_S = TypeVar("_S", bound="SavedModel")


class SavedModel:
    """What :func:`save_model` and :func:`load_model` need of a model class: the base of
    :class:`~hgpdm_torch.models.GPDM` and :class:`~hgpdm_torch.models.LinearIDDM` (this module
    imports neither; they register themselves in :mod:`hgpdm_torch.models`).

    A subclass provides ``config()`` (its plain constructor options), ``_data_arguments()``
    (training data), ``state_dict()`` / ``load_state_dict()`` and ``_saved_dtype()``; it is
    rebuilt as ``cls(**data, **config, dtype=dtype)`` unless it overrides :meth:`_from_saved`.
    Creating an instance records the constructor arguments ``save`` may need (a subclass's own,
    and those named in :attr:`object_arguments`).
    """

    #: Constructor arguments of the class that may be objects ``config()`` cannot hold; an
    #: instance lists those it got in ``_object_arguments``.
    object_arguments: ClassVar[tuple[str, ...]] = ()
    #: ``{old keyword: new keyword}``: constructor keywords renamed since files were saved;
    #: loading renames them in a file's configuration and data before rebuilding the model.
    config_renames: ClassVar[dict[str, str]] = {}

    def __new__(cls, *args: Any, **kwargs: Any) -> Any:
        self = super().__new__(cls)
        object.__setattr__(self, "_init_arguments", _capture(cls, args, kwargs))
        return self

    def config(self) -> dict[str, Any]:
        raise NotImplementedError

    def _data_arguments(self) -> dict[str, Any]:
        raise NotImplementedError

    def _saved_dtype(self) -> torch.dtype:
        raise NotImplementedError

    @classmethod
    def _from_saved(
        cls, data: dict[str, Any], config: dict[str, Any], dtype: torch.dtype,
        state: dict[str, Any],
    ) -> SavedModel:  # fmt: skip
        """The model :func:`load_model` rebuilds before loading ``state`` into it."""
        return cls(**data, **config, dtype=dtype)

    @classmethod
    def load(cls: type[_S], path: str | os.PathLike[str], *, model: _S | None = None) -> _S:
        """:func:`~hgpdm_torch.models.load_model`, for a model that must be an instance of
        ``cls``: ``HGPDM.load(path)``, or ``HGPDM.load(path, model=HGPDM(...))`` to load the
        saved state into a model your code built.

        Raises:
            ModelFileError: see :func:`~hgpdm_torch.models.load_model`, or the file holds a
                model of another class (e.g. ``HGPDM.load`` of a saved plain GPDM).
            TypeError: ``model`` is not a ``cls``.
        """
        if model is not None and not isinstance(model, cls):
            raise TypeError(f"model must be a {cls.__qualname__}, got {type(model).__qualname__}")
        loaded = load_model(path, model=model)
        if not isinstance(loaded, cls):
            raise ModelFileError(
                f"{path}: holds a {type(loaded).__qualname__}, not a {cls.__qualname__}; "
                "use hgpdm_torch.models.load_model to load any registered class"
            )
        return loaded


M = TypeVar("M", bound=type[SavedModel])

_REGISTRY: dict[str, type[SavedModel]] = {}


# --------------------------------------------------------------------------------- registry
@overload
def register_model(cls: M, *, name: str | None = None) -> M: ...


@overload
def register_model(cls: None = None, *, name: str | None = None) -> Callable[[M], M]: ...


def register_model(cls: M | None = None, *, name: str | None = None) -> M | Callable[[M], M]:
    """Allow :func:`load_model` to rebuild a model class; usable as a class decorator.

    A file stores the name a class is registered under, and loading looks that name up here:
    no module named by a file is ever imported. A class must be registered before its models
    are saved and before the files are loaded (e.g. at the top of the module defining it)::

        @register_model
        class MyGPDM(GPDM):
            def __init__(self, sequences, latent_dim=3, *, damping=0.5, kernel=None, **kwargs):
                super().__init__(sequences, latent_dim, **kwargs)
                ...

        register_model(OtherGPDM, name="mylab.OtherGPDM")

    The class is rebuilt as ``cls(**data, **config, dtype=dtype)`` followed by
    ``load_state_dict``. The arguments its constructor takes beyond those of the hgpdm_torch
    classes it derives from are recorded when a model is built: plain values (``damping=0.25``)
    are saved in the configuration and passed back on loading; an object (``kernel=Matern()``)
    cannot be, so loading that file needs ``load_model(path, model=MyGPDM(..., kernel=...))``
    and :class:`ModelFileError` names the argument otherwise. A value that changes after
    construction belongs in ``self._config`` (what :meth:`GPDM.config` returns), which is saved
    as it is when saving. A constructor keyword renamed later is listed in the class's
    ``config_renames`` (``{"old": "new"}``) so that older files still rebuild.

    Args:
        cls: a subclass of :class:`~hgpdm_torch.models.GPDM` or
            :class:`~hgpdm_torch.models.LinearIDDM` (or either itself); omit it to get a
            decorator, e.g. ``@register_model(name="mylab.MyGPDM")``.
        name: the name stored in files (default: the class's ``__qualname__``). Names are
            global: choose a qualified one if another package may use the same class name.

    Returns:
        ``cls`` unchanged (or the decorator).

    Raises:
        TypeError: ``cls`` is not a GPDM or LinearIDDM subclass.
        ValueError: ``name`` is empty, is taken by another class, or ``cls`` is already
            registered under another name. Re-registering a class with the same module and
            qualified name (re-running a notebook cell, reloading a module) replaces the old
            class object.
    """
    if cls is None:
        return lambda c: register_model(c, name=name)
    if not (isinstance(cls, type) and issubclass(cls, SavedModel)):
        raise TypeError(f"register_model needs a subclass of GPDM or LinearIDDM, got {cls!r}")
    key = cls.__qualname__ if name is None else name
    if not isinstance(key, str) or not key:
        raise ValueError(f"name must be a non-empty str, got {name!r}")
    for other_name, other in _REGISTRY.items():
        if other is cls and other_name != key:
            raise ValueError(f"{_describe(cls)} is already registered as {other_name!r}")
    old = _REGISTRY.get(key)
    if old is not None and old is not cls and _describe(old) != _describe(cls):
        raise ValueError(
            f"the model name {key!r} is already registered for {_describe(old)}; register "
            f"{_describe(cls)} under another name: register_model(cls, name=...)"
        )
    _REGISTRY[key] = cls
    return cls


def registered_models() -> dict[str, type[SavedModel]]:
    """A copy of the registry: the names a file may store, with the class each one loads."""
    return dict(_REGISTRY)


def _describe(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def _registered_name(cls: type[SavedModel]) -> str:
    for key, registered in _REGISTRY.items():
        if registered is cls:
            return key
    raise TypeError(
        f"{_describe(cls)} is not a registered model class, so a saved file could not be "
        f"loaded; register it first: decorate the class with @register_model or call "
        f"hgpdm_torch.models.register_model({cls.__qualname__})"
    )


# --------------------------------------------------------------------------------- writing
def _saved_arguments(
    model: SavedModel, data: Mapping[str, Any]
) -> tuple[dict[str, Any], dict[str, str]]:
    """The plain configuration and the ``{argument: type name}`` of the object arguments of
    ``model`` (without the dtype)."""
    config: dict[str, Any] = {}
    user: dict[str, str] = {}
    for key, value in model.config().items():
        try:
            config[key] = _plain(value)
        except _NotPlain:  # an override of config() returning an object
            user[key] = type(value).__qualname__
    objects = list(getattr(model, "_object_arguments", ()))
    captured = getattr(model, "_init_arguments", None)
    if captured is None:  # built before arguments were recorded (an old pickle)
        user.update({name: "object" for name in objects if name not in config})
        return config, user
    _, library, _ = _class_arguments(type(model))
    for name, value in captured.items():
        if name in config or name in data or name in user or name == "dtype":
            continue
        if name in library and name not in objects:
            continue  # the library's own option, held by config() where it matters
        if isinstance(value, _Unrecorded):
            user[name] = value.type_name
        else:
            config[name] = value
    return config, user


def save_model(model: SavedModel, path: str | os.PathLike[str]) -> None:
    """Write ``model`` to ``path`` in the format above (what :meth:`GPDM.save` and
    :meth:`LinearIDDM.save` call).

    Any model of a registered class is saved, custom kernels, priors and object arguments
    included: their parameters are in the state, and the file lists the arguments that loading
    needs from your code (``user_arguments``). The file is written beside ``path`` under a
    temporary name and then renamed over it, so an interrupted save never leaves a half-written
    file in place of a good one.

    Raises:
        TypeError: the model's class is not registered (see :func:`register_model`).
        FileNotFoundError: the folder of ``path`` does not exist.
        NotADirectoryError: the folder of ``path`` is a file.
        IsADirectoryError: ``path`` is a folder.
    """
    name = _registered_name(type(model))
    data = model._data_arguments()
    config, user = _saved_arguments(model, data)
    config["dtype"] = str(model._saved_dtype()).removeprefix("torch.")
    path = Path(path)
    if not path.parent.exists():
        raise FileNotFoundError(
            f"cannot save the model to {path}: the folder {path.parent} does not exist; "
            "create it first"
        )
    if not path.parent.is_dir():
        raise NotADirectoryError(
            f"cannot save the model to {path}: {path.parent} is a file, not a folder"
        )
    if path.is_dir():
        raise IsADirectoryError(f"cannot save the model to {path}: it is a folder, not a file")
    blob = {
        "format": FORMAT_VERSION,
        "class": name,
        "config": config,
        "data": data,
        "state_dict": model.state_dict(),
        "user_arguments": user,
    }
    buffer = io.BytesIO()
    torch.save(blob, buffer)
    payload = buffer.getvalue()
    head = MAGIC + _HEADER.pack(FORMAT_VERSION, len(payload))
    digest = hashlib.sha256(head + payload).digest()
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(6)}.tmp")
    try:
        with open(tmp, "xb") as f:
            f.write(head + digest + payload)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


# --------------------------------------------------------------------------------- reading
def _read_payload(path: Path) -> tuple[int, bytes]:
    """Check magic, version, length and checksum; return the version and the payload bytes."""
    with open(path, "rb") as f:
        prefix = f.read(_PREFIX_SIZE)
        if not prefix:
            raise ModelFileError(f"{path}: the file is empty, not a saved model")
        magic = prefix[: len(MAGIC)]
        if magic != MAGIC:
            if MAGIC.startswith(prefix):
                raise ModelFileError(f"{path}: the file is truncated ({len(prefix)} bytes)")
            hint = ""
            if prefix.startswith(b"PK\x03\x04"):
                hint = (
                    " (it is a plain torch.save archive; files written by hgpdm-torch before "
                    "format version 1 carry no checksum and are not loaded)"
                )
            raise ModelFileError(f"{path}: not an hgpdm-torch model file{hint}")
        if len(prefix) < len(MAGIC) + _HEADER.size:
            raise ModelFileError(f"{path}: the file is truncated inside its header")
        version, length = _HEADER.unpack_from(prefix, len(MAGIC))
        if version > FORMAT_VERSION:
            raise ModelFileError(
                f"{path}: written in model file format version {version}, newer than this "
                f"release reads (1 .. {FORMAT_VERSION}); upgrade hgpdm-torch to load it"
            )
        if version < 1:
            raise ModelFileError(f"{path}: unknown model file format version {version}")
        if len(prefix) < _PREFIX_SIZE:
            raise ModelFileError(f"{path}: the file is truncated inside its header")
        size = os.fstat(f.fileno()).st_size
        if size != _PREFIX_SIZE + length:
            problem = "truncated" if size < _PREFIX_SIZE + length else "longer than its header says"
            raise ModelFileError(
                f"{path}: the file is {problem} ({size} bytes, expected "
                f"{_PREFIX_SIZE + length}); it is corrupted or was not copied completely"
            )
        payload = f.read(length)
    expected = prefix[len(MAGIC) + _HEADER.size :]
    if hashlib.sha256(prefix[: len(MAGIC) + _HEADER.size] + payload).digest() != expected:
        raise ModelFileError(f"{path}: checksum mismatch; the file is corrupted")
    return version, payload


@dataclass
class _Saved:
    """A validated payload."""

    name: str
    cls: type[SavedModel] | None  # None: not registered (allowed with model=)
    config: dict[str, Any]
    data: dict[str, Any]
    state: dict[str, torch.Tensor]
    dtype: torch.dtype
    user: dict[str, str]


def _check_blob(path: Path, version: int, blob: Any, *, registered: bool) -> _Saved:
    """Validate the structure of a verified payload of format ``version``. The class must be
    registered when ``registered``."""
    keys = _PAYLOAD_KEYS[version]
    if not isinstance(blob, dict) or set(blob) != keys:
        got = sorted(map(str, blob)) if isinstance(blob, dict) else type(blob).__name__
        missing = f" (missing {sorted(keys - set(blob))})" if isinstance(blob, dict) else ""
        raise ModelFileError(
            f"{path}: the format-{version} payload must be a dict with keys {sorted(keys)}, "
            f"got {got}{missing}"
        )
    if version >= 2 and (type(blob["format"]) is not int or blob["format"] != version):
        raise ModelFileError(
            f"{path}: the payload says format {blob['format']!r}, its header {version}"
        )
    name = blob["class"]
    cls = _REGISTRY.get(name) if isinstance(name, str) else None
    if cls is None and (registered or not isinstance(name, str)):
        raise ModelFileError(
            f"{path}: the file holds a model of class {name!r}, which is not registered "
            f"(registered: {sorted(_REGISTRY)}). If it is your own GPDM or LinearIDDM subclass, "
            "register it before loading: decorate the class with "
            f"@hgpdm_torch.models.register_model, or call register_model(cls, name={name!r}); "
            "or build the model yourself and pass it: load_model(path, model=...)"
        )
    config, data, state = blob["config"], blob["data"], blob["state_dict"]
    user = blob["user_arguments"] if version >= 2 else {}
    parts = {"config": config, "data": data, "state_dict": state, "user_arguments": user}
    for key, value in parts.items():
        if not isinstance(value, Mapping) or not all(isinstance(k, str) for k in value):
            raise ModelFileError(f"{path}: {key} must be a dict with str keys")
    if not all(isinstance(v, str) for v in user.values()):
        raise ModelFileError(f"{path}: user_arguments must map names to type names")
    config = dict(config)
    if version >= 2:
        if not _is_plain(config):
            raise ModelFileError(f"{path}: config must hold plain (JSON-able) values only")
        dtype_name = config.pop("dtype", None)
    else:
        dtype_name = blob["dtype"]
        if "dtype" in config:
            raise ModelFileError(f"{path}: config and data name the same constructor argument")
    dtype = _DTYPES.get(dtype_name) if isinstance(dtype_name, str) else None
    if dtype is None:
        raise ModelFileError(f"{path}: dtype must be one of {sorted(_DTYPES)}, got {dtype_name!r}")
    if not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise ModelFileError(f"{path}: every entry of state_dict must be a tensor")
    if set(config) & set(data) or "dtype" in data:
        raise ModelFileError(f"{path}: config and data name the same constructor argument")
    return _Saved(name, cls, config, dict(data), state, dtype, dict(user))


def _same(a: Any, b: Any) -> bool:
    """Exact equality of nested tensors, lists, tuples, dicts and scalars."""
    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        return (
            isinstance(a, torch.Tensor)
            and isinstance(b, torch.Tensor)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and bool(torch.equal(a.cpu(), b.cpu()))
        )
    if isinstance(a, list | tuple):
        return (
            isinstance(b, list | tuple)
            and len(a) == len(b)
            and all(_same(x, y) for x, y in zip(a, b, strict=True))
        )
    if isinstance(a, Mapping):
        return isinstance(b, Mapping) and set(a) == set(b) and all(_same(a[k], b[k]) for k in a)
    return type(a) is type(b) and a == b


def _rename(path: Path, saved: _Saved, cls: type) -> None:
    """Apply ``cls.config_renames`` to the saved configuration, data and argument names."""
    for old, new in getattr(cls, "config_renames", {}).items():
        for part in (saved.config, saved.data, saved.user):
            if old in part:
                if new in part:
                    raise ModelFileError(f"{path}: the file names both {old!r} and {new!r}")
                part[new] = part.pop(old)


def _check_given(path: Path, saved: _Saved, model: Any) -> None:
    """The model given to :func:`load_model` must match the file where the file can tell."""
    if not isinstance(model, SavedModel):
        raise TypeError(
            f"model must be a GPDM or LinearIDDM (a SavedModel), got {type(model).__qualname__}"
        )
    kind = type(model).__qualname__
    if saved.cls is not None and not isinstance(model, saved.cls):
        raise ModelFileError(
            f"{path}: holds a {saved.name}, but the model given is a {kind}; build a "
            f"{saved.cls.__qualname__}"
        )
    if model._saved_dtype() != saved.dtype:
        raise ModelFileError(
            f"{path}: holds a {saved.dtype} model, the model given is {model._saved_dtype()}; "
            f"build it with dtype={saved.dtype}"
        )
    _rename(path, saved, type(model))
    mine, _ = _saved_arguments(model, model._data_arguments())
    common = mine.keys() & saved.config.keys()
    differ = sorted(k for k in common if not _same(mine[k], saved.config[k]))
    if differ:
        shown = ", ".join(f"{k} (file {saved.config[k]!r}, model {mine[k]!r})" for k in differ)
        raise ModelFileError(
            f"{path}: the model given was built with other options than the saved {saved.name}: "
            f"{shown}; build it with the saved ones"
        )


def _load_state(path: Path, model: Any, state: dict[str, torch.Tensor], what: str) -> None:
    """Load ``state`` into ``model`` strictly: every key of each, every shape."""
    hint = (
        "build the model with the same kernels, priors and options as the saved one"
        if what.startswith("the model given")
        else "if the model was built with objects of your own code, build it the same way and "
        "pass it: load_model(path, model=...)"
    )
    try:
        if isinstance(model, torch.nn.Module):
            result = model.load_state_dict(state, strict=False)
            missing, unexpected = list(result.missing_keys), list(result.unexpected_keys)
        else:
            model.load_state_dict(state)
            missing, unexpected = [], []
    except RuntimeError as err:
        raise ModelFileError(f"{path}: the saved state does not fit {what}: {err}; {hint}") from err
    if missing or unexpected:
        parts = [f"missing from the file: {missing}"] if missing else []
        parts += [f"in the file but not in the model: {unexpected}"] if unexpected else []
        raise ModelFileError(
            f"{path}: the saved state does not fit {what}: {'; '.join(parts)}; {hint}"
        )


def load_model(path: str | os.PathLike[str], *, model: Any = None) -> Any:
    """Load a model saved with :meth:`GPDM.save` or :meth:`LinearIDDM.save` (any format
    version up to :data:`FORMAT_VERSION`): same class, data, parameters and buffers.

    Without ``model``, the model is rebuilt by the registered class the file names (looked up,
    never imported) from the saved training data and plain configuration, on the CPU, and the
    saved state is loaded into it. A model built with objects a file cannot hold (a custom
    gpytorch kernel, priors, a back-constraint module, a subclass's object argument) is
    rebuilt by your code instead, with the same objects: ``load_model(path, model=HGPDM(
    sequences, intentions, 2, measurement=my_kernel))`` checks that it matches the file
    (class, dtype, the saved plain options) and loads the saved state into it (every key, every
    shape), so its parameters, the kernels' hyperparameters and the learned latent states are
    the saved ones. The payload is read with ``torch.load(..., weights_only=True)``.

    Args:
        path: a file written by :meth:`GPDM.save` or :meth:`LinearIDDM.save`.
        model: a model your code built to take the saved state (its class need not be
            registered); ``None`` (default) rebuilds it from the file.

    Returns:
        The model: ``model`` itself when given, else an instance of the registered class the
        file names.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        TypeError: ``model`` is not a GPDM or LinearIDDM.
        ModelFileError: the file is empty, truncated, foreign, corrupted (checksum mismatch), of
            an unknown format version, or names an unregistered class; it needs constructor
            arguments only your code can build (the message names them: pass ``model=``); its
            configuration and data do not rebuild the model; its state does not fit the model
            (the missing and unexpected keys are named); the model given is of another class,
            dtype or plain options; or the training data and the saved state differ.
    """
    path = Path(path)
    version, payload = _read_payload(path)
    try:
        blob = torch.load(io.BytesIO(payload), map_location="cpu", weights_only=True)
    except Exception as err:  # any unpickling failure means a bad file
        raise ModelFileError(f"{path}: the payload cannot be read: {err}") from err
    saved = _check_blob(path, version, blob, registered=model is None)
    if model is not None:
        _check_given(path, saved, model)
        what = f"the model given ({type(model).__qualname__})"
    else:
        cls = saved.cls
        assert cls is not None  # _check_blob
        _rename(path, saved, cls)
        if saved.user:
            names = sorted(saved.user)
            shown = ", ".join(f"{k} (a {saved.user[k]})" for k in names)
            raise ModelFileError(
                f"{path}: the {saved.name} was built with objects a file cannot hold, the "
                f"constructor arguments {shown}. Build the model in your code with the same "
                f"arguments, then load the saved state into it: load_model(path, "
                f"model={cls.__qualname__}(..., {', '.join(f'{k}=...' for k in names)}))"
            )
        try:
            model = cls._from_saved(saved.data, saved.config, saved.dtype, saved.state)
        except (TypeError, ValueError, RuntimeError) as err:
            raise ModelFileError(
                f"{path}: the saved configuration and data do not rebuild a {saved.name}: {err}; "
                f"build the model yourself and pass it: load_model(path, model=...)"
            ) from err
        what = f"the {saved.name} rebuilt from the configuration and data"
    _load_state(path, model, saved.state, what)
    if not _same(model._data_arguments(), saved.data):
        raise ModelFileError(
            f"{path}: the training data saved with the configuration differ from the training "
            f"data in the saved state (observations, lengths or intentions); refusing an "
            f"inconsistent model"
        )
    return model
