"""Safe persistence of models: a versioned, checksummed file format and an allow-list of classes.

:meth:`GPDM.save <hgpdm_torch.models.GPDM.save>` writes, and :func:`load_model` reads, one file:

=========  ======  ===========================================================================
offset     bytes   content
=========  ======  ===========================================================================
0          16      :data:`MAGIC`, ``b"\\x89hgpdm-torch\\r\\n\\x1a\\n"``
16         4       format version, unsigned little-endian (:data:`FORMAT_VERSION`)
20         8       payload length P in bytes, unsigned little-endian
28         32      SHA-256 of bytes ``0 .. 28`` followed by the payload (everything but itself)
60         P       payload: ``torch.save`` of ``{"class", "config", "data", "state_dict",
                   "dtype"}``
=========  ======  ===========================================================================

The payload holds everything that determines the model: the registered class name, the
constructor configuration (:meth:`GPDM.config`), the training data (``_data_arguments``), the
``state_dict`` (parameters and buffers) and the dtype name. Loading checks, in this order, the
magic bytes, the version (a newer version is refused before anything else is read, as its layout
may differ), the length, the checksum, the payload's structure, the class name against the
registry, and finally that the training data stored beside the configuration equal the
observations in the ``state_dict``. Every failure raises :class:`ModelFileError`.

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

import copy
import hashlib
import inspect
import io
import os
import secrets
import struct
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, TypeVar, overload

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
FORMAT_VERSION = 1
_HEADER = struct.Struct("<IQ")  # version, payload length
_DIGEST_SIZE = hashlib.sha256().digest_size
_PREFIX_SIZE = len(MAGIC) + _HEADER.size + _DIGEST_SIZE
_PAYLOAD_KEYS = frozenset({"class", "config", "data", "state_dict", "dtype"})
_DTYPES = {
    "float16": torch.float16,
    "bfloat16": torch.bfloat16,
    "float32": torch.float32,
    "float64": torch.float64,
}


class ModelFileError(ValueError):
    """A file is not a model file this release can load: foreign, empty, truncated, corrupted,
    of an unknown format version, naming an unregistered class, or inconsistent."""


_S = TypeVar("_S", bound="SavedModel")


class SavedModel:
    """What :func:`save_model` and :func:`load_model` need of a model class: the base of
    :class:`~hgpdm_torch.models.GPDM` and :class:`~hgpdm_torch.models.LinearIDDM` (this module
    imports neither; they register themselves in :mod:`hgpdm_torch.models`).

    A subclass provides ``config()`` (constructor options), ``_data_arguments()`` (training
    data), ``state_dict()`` / ``load_state_dict()`` and ``_saved_dtype()``; it is rebuilt as
    ``cls(**data, **config, dtype=dtype)`` unless it overrides :meth:`_from_saved`.
    """

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
    def load(cls: type[_S], path: str | os.PathLike[str]) -> _S:
        """Load a model written by ``save``; it must be an instance of ``cls``.

        Raises:
            ModelFileError: see :func:`~hgpdm_torch.models.load_model`, or the file holds a
                model of another class (e.g. ``HGPDM.load`` of a saved plain GPDM).
        """
        model = load_model(path)
        if not isinstance(model, cls):
            raise ModelFileError(
                f"{path}: holds a {type(model).__qualname__}, not a {cls.__qualname__}; "
                "use hgpdm_torch.models.load_model to load any registered class"
            )
        return model


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
            ...

        register_model(OtherGPDM, name="mylab.OtherGPDM")

    The class is rebuilt as ``cls(**model._data_arguments(), **model.config(), dtype=dtype)``
    followed by ``load_state_dict``: a subclass whose constructor takes more arguments adds them
    to ``self._config`` (constructor options) or overrides ``_data_arguments`` (data);
    ``save`` refuses (``TypeError``) a class whose constructor takes an argument of its own
    that neither holds, since loading would silently give it its default::

        @register_model
        class MyGPDM(GPDM):
            def __init__(self, sequences, latent_dim=3, *, extra=5, **kwargs):
                super().__init__(sequences, latent_dim, **kwargs)
                self.extra = extra
                self._config["extra"] = extra  # saved, and passed back on load

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
def save_model(model: SavedModel, path: str | os.PathLike[str]) -> None:
    """Write ``model`` to ``path`` in the format above (what :meth:`GPDM.save` and
    :meth:`LinearIDDM.save` call).

    The file is written beside ``path`` under a temporary name and then renamed over it, so an
    interrupted save never leaves a half-written file in place of a good one.

    Raises:
        TypeError: the model's class is not registered (see :func:`register_model`), or
            loading could not rebuild it as saved: its constructor refuses the saved
            arguments, or takes one of its own that is not saved (add it to the configuration,
            see :func:`register_model`).
        FileNotFoundError: the folder of ``path`` does not exist.
        NotADirectoryError: the folder of ``path`` is a file.
        IsADirectoryError: ``path`` is a folder.
    """
    name = _registered_name(type(model))
    config, data = copy.deepcopy(model.config()), model._data_arguments()
    _check_rebuild(type(model), config, data)
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
        "class": name,
        "config": config,
        "data": data,
        "state_dict": model.state_dict(),
        "dtype": str(model._saved_dtype()).removeprefix("torch."),
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


def _check_rebuild(cls: type[SavedModel], config: dict[str, Any], data: dict[str, Any]) -> None:
    """Refuse to save a model that :func:`load_model` would rebuild differently.

    A class rebuilt the default way, ``cls(**data, **config, dtype=dtype)`` (one that does not
    override :meth:`SavedModel._from_saved`), must take every saved argument, and every
    argument its own constructor adds to those of the hgpdm_torch classes it derives from must
    be saved: otherwise loading would fail, or silently rebuild the model with that argument's
    default.

    Raises:
        TypeError: naming the class, the arguments and what to do.
    """
    if getattr(cls._from_saved, "__func__", None) is not SavedModel._from_saved.__func__:
        return  # the class rebuilds itself; it knows what it saved
    fix = (
        "store each in the configuration in __init__ (self._config[name] = value, or override "
        "config()) or, for training data, in _data_arguments(); or override _from_saved"
    )
    try:
        inspect.signature(cls).bind(**data, **config, dtype=None)
    except TypeError as err:
        raise TypeError(
            f"cannot save a {cls.__qualname__}: load_model rebuilds it as "
            f"{cls.__qualname__}(**data, **config, dtype=...) with the saved arguments "
            f"{sorted(data) + sorted(config)}, which its constructor refuses ({err}); let "
            "__init__ take them (e.g. **kwargs passed on to super().__init__) or override "
            "_from_saved"
        ) from None
    library, own = set(), {}
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        if init is None or klass is SavedModel:
            continue
        names = [
            p.name
            for p in list(inspect.signature(init).parameters.values())[1:]
            if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
        ]
        if klass.__module__.split(".")[0] == "hgpdm_torch":
            library.update(names)
        else:
            own.update(dict.fromkeys(names))
    unsaved = [n for n in own if n not in library and n not in config and n not in data]
    if unsaved:
        raise TypeError(
            f"cannot save a {cls.__qualname__}: its constructor takes {unsaved}, which "
            f"save() does not store, so load_model would rebuild it with their defaults; {fix}"
        )


# --------------------------------------------------------------------------------- reading
def _read_payload(path: Path) -> bytes:
    """Check magic, version, length and checksum; return the verified payload bytes."""
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
    return payload


def _check_blob(path: Path, blob: Any) -> tuple[type[SavedModel], dict, dict, dict, torch.dtype]:
    """Validate the structure of a verified payload; return class, config, data, state, dtype."""
    if not isinstance(blob, dict) or set(blob) != _PAYLOAD_KEYS:
        keys = sorted(map(str, blob)) if isinstance(blob, dict) else type(blob).__name__
        raise ModelFileError(
            f"{path}: the payload must be a dict with keys {sorted(_PAYLOAD_KEYS)}, got {keys}"
        )
    name = blob["class"]
    cls = _REGISTRY.get(name) if isinstance(name, str) else None
    if cls is None:
        raise ModelFileError(
            f"{path}: the file holds a model of class {name!r}, which is not registered "
            f"(registered: {sorted(_REGISTRY)}). If it is your own GPDM or LinearIDDM subclass, "
            "register it before loading: decorate the class with "
            f"@hgpdm_torch.models.register_model, or call register_model(cls, name={name!r})"
        )
    dtype = _DTYPES.get(blob["dtype"]) if isinstance(blob["dtype"], str) else None
    if dtype is None:
        raise ModelFileError(
            f"{path}: dtype must be one of {sorted(_DTYPES)}, got {blob['dtype']!r}"
        )
    config, data, state = blob["config"], blob["data"], blob["state_dict"]
    for key, value in (("config", config), ("data", data), ("state_dict", state)):
        if not isinstance(value, Mapping) or not all(isinstance(k, str) for k in value):
            raise ModelFileError(f"{path}: {key} must be a dict with str keys")
    if not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise ModelFileError(f"{path}: every entry of state_dict must be a tensor")
    if set(config) & set(data) or "dtype" in config or "dtype" in data:
        raise ModelFileError(f"{path}: config and data name the same constructor argument")
    return cls, dict(config), dict(data), state, dtype


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


def load_model(path: str | os.PathLike[str]) -> Any:
    """Rebuild a model saved with :meth:`GPDM.save` or :meth:`LinearIDDM.save`: same class,
    data, parameters and buffers (statistics).

    The class is looked up by its saved name among the registered classes
    (:func:`register_model`); nothing named by the file is imported, and the payload is read
    with ``torch.load(..., weights_only=True)``. The model is rebuilt on the CPU.

    Args:
        path: a file written by :meth:`GPDM.save` or :meth:`LinearIDDM.save`.

    Returns:
        The model, an instance of the registered class the file names.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ModelFileError: the file is empty, truncated, foreign, corrupted (checksum mismatch), of
            an unknown format version, names an unregistered class, does not rebuild the
            model, or its training data and saved observations differ.
    """
    path = Path(path)
    payload = _read_payload(path)
    try:
        blob = torch.load(io.BytesIO(payload), map_location="cpu", weights_only=True)
    except Exception as err:  # any unpickling failure means a bad file
        raise ModelFileError(f"{path}: the payload cannot be read: {err}") from err
    cls, config, data, state, dtype = _check_blob(path, blob)
    try:
        model = cls._from_saved(data, config, dtype, state)
    except (TypeError, ValueError, RuntimeError) as err:
        raise ModelFileError(
            f"{path}: the saved configuration and data do not rebuild a {blob['class']}: {err}"
        ) from err
    try:
        model.load_state_dict(state)
    except RuntimeError as err:
        raise ModelFileError(
            f"{path}: the saved state does not fit the {blob['class']} rebuilt from the "
            f"configuration and data: {err}"
        ) from err
    if not _same(model._data_arguments(), data):
        raise ModelFileError(
            f"{path}: the training data saved with the configuration differ from the training "
            f"data in the saved state (observations, lengths or intentions); refusing an "
            f"inconsistent model"
        )
    return model
