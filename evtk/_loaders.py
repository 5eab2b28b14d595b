"""Arrays and images from files a user hands evtk, sized against the memory budget before anything is decoded.

Nothing here runs code from a file: ``.npy`` files are read with pickles
refused, and a pickle (CIFAR-10's python batches) is walked opcode by opcode
into plain values (:func:`read_plain_pickle`), never unpickled: no module is
imported and no callable the file names is called.
"""

from __future__ import annotations

import os
import pickletools

import numpy as np

from .errors import EvtkError, FormatError
from .limits import require_memory

__all__ = ["read_image", "read_npy", "read_plain_pickle"]


# -- .npy ---------------------------------------------------------------------------------

def read_npy(path, what="array") -> np.ndarray:
    """A ``.npy`` array, its declared size checked against the file and the memory budget before reading.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.npy`` file.
    what : str
        What the array is, for messages ("kernel", "target").

    Returns
    -------
    numpy.ndarray
        The array; object arrays (pickles) are refused.
    """
    path = os.fspath(path)
    fmt = np.lib.format
    try:
        with open(path, "rb") as fh:
            version = fmt.read_magic(fh)
            if version == (1, 0):
                shape, _, dtype = fmt.read_array_header_1_0(fh)
            elif version == (2, 0):
                shape, _, dtype = fmt.read_array_header_2_0(fh)
            else:
                raise FormatError(path, 6, f"unsupported .npy version {version[0]}.{version[1]}")
            start = fh.tell()
            size = os.fstat(fh.fileno()).st_size
    except FormatError:
        raise
    except (OSError, ValueError, SyntaxError) as exc:
        raise EvtkError(f"cannot read {what} {path!r}: {exc}") from None
    if dtype.hasobject:
        raise FormatError(path, start, f"the {what} holds Python objects (a pickle), which evtk does not load")
    need = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if size - start != need:
        raise FormatError(path, start, f"the header declares {shape} {dtype} ({need:,} bytes) but the file holds "
                                       f"{size - start:,} bytes of data")
    require_memory(need, f"the {what} {path}")
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise EvtkError(f"cannot read {what} {path!r}: {exc}") from None


# -- images -------------------------------------------------------------------------------

def read_image(path, what="image") -> np.ndarray:
    """An image file (PNG, JPEG, BMP, ...) as an array, its declared size checked against the budget first.

    The header's width and height are read before any pixel is decoded; the
    budget covers the decoded pixels and the float copy callers make of them.

    Parameters
    ----------
    path : str or os.PathLike
        The image.
    what : str
        What the image is, for messages.

    Returns
    -------
    numpy.ndarray
        (h, w) for grey images, (h, w, bands) for colour (RGB or RGBA; palette
        and CMYK images are converted to RGB(A)), the first frame of an animation.
    """
    import warnings

    from PIL import Image

    path = os.fspath(path)
    with warnings.catch_warnings():  # the budget below is the check; Pillow's own warning is noise
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        try:
            im: Image.Image = Image.open(path)
        except Exception as exc:  # noqa: BLE001 - any reader failure is the user's file
            raise EvtkError(f"cannot read {what} {path!r}: {exc}") from None
    with im:
        w_px, h_px = im.size
        # decoded pixels (up to 4 bands, up to 4 bytes each) and a float64 copy of them
        require_memory(int(w_px) * int(h_px) * 4 * (4 + 8), f"the {what} {path} ({w_px}x{h_px} pixels)")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", Image.DecompressionBombWarning)
                if im.mode not in ("1", "L", "LA", "I", "I;16", "F", "RGB", "RGBA"):
                    im = im.convert("RGBA" if "A" in im.mode or "transparency" in im.info else "RGB")
                arr = np.asarray(im)
        except Exception as exc:  # noqa: BLE001
            raise EvtkError(f"cannot read {what} {path!r}: {exc}") from None
    if arr.ndim not in (2, 3) or arr.size == 0:
        raise EvtkError(f"cannot read {what} {path!r}: it decodes to an array of shape {arr.shape}")
    return arr


# -- pickles, walked and never run ------------------------------------------------------------

class _Global:
    """A name a pickle refers to (never imported)."""

    def __init__(self, kind):
        self.kind = kind


class _Dtype:
    """``numpy.dtype(descr)`` as a pickle describes it (never constructed from the file's text)."""

    def __init__(self, descr):
        self.descr = descr


class _Array:
    """``numpy.core.multiarray._reconstruct(...)``: the array's bytes arrive with BUILD."""

    def __init__(self):
        self.value = None


# the only names a CIFAR-10 batch refers to; each is interpreted here, none is looked up
_GLOBALS = {
    "numpy.core.multiarray _reconstruct": "reconstruct",
    "numpy._core.multiarray _reconstruct": "reconstruct",
    "numpy ndarray": "ndarray",
    "numpy dtype": "dtype",
    "numpy.core.numeric _frombuffer": "frombuffer",
    "numpy._core.numeric _frombuffer": "frombuffer",
    "_codecs encode": "encode",
}
_DTYPES = {"u1": np.uint8, "|u1": np.uint8}
_STRING_OPS = {"STRING", "BINSTRING", "SHORT_BINSTRING"}  # Python 2 str: bytes (as pickle.load(encoding="bytes"))
_VALUE_OPS = {"BINBYTES", "SHORT_BINBYTES", "BINBYTES8", "BINUNICODE", "SHORT_BINUNICODE", "BINUNICODE8", "UNICODE",
              "INT", "BININT", "BININT1", "BININT2", "LONG", "LONG1", "LONG4", "BINFLOAT", "FLOAT"}


def _array(path, pos, buf, dtype, shape, fortran=False):
    if not isinstance(dtype, _Dtype) or dtype.descr not in _DTYPES:
        raise FormatError(path, pos, "the pickle holds an array of a type evtk does not read (bytes only)")
    if (not isinstance(shape, tuple) or not all(isinstance(d, int) and d >= 0 for d in shape)
            or not isinstance(buf, (bytes, bytearray)) or fortran not in (False, 0)):
        raise FormatError(path, pos, "the pickle holds an array in a form evtk does not read")
    dt = np.dtype(_DTYPES[dtype.descr])
    if int(np.prod(shape, dtype=object)) * dt.itemsize != len(buf):
        raise FormatError(path, pos, f"an array of shape {shape} does not fit its {len(buf):,} bytes")
    return np.frombuffer(bytes(buf), dtype=dt).reshape(shape)


def _reduce(path, pos, func, args):
    kind = func.kind if isinstance(func, _Global) else None
    if not isinstance(args, tuple):
        kind = None
    if kind == "reconstruct" and len(args) == 3 and isinstance(args[0], _Global) and args[0].kind == "ndarray":
        return _Array()
    if kind == "dtype" and len(args) == 3 and isinstance(args[0], str):
        return _Dtype(args[0])
    if kind == "frombuffer" and len(args) == 4:
        return _array(path, pos, args[0], args[1], args[2], args[3] == "F")
    if kind == "encode" and len(args) == 2 and isinstance(args[0], str) and args[1] in ("latin1", "latin-1"):
        return args[0].encode("latin-1")
    raise FormatError(path, pos, "the pickle calls something other than building an array: refused (evtk never "
                                 "runs code from a file)")


def _build(path, pos, obj, state):
    if isinstance(obj, _Dtype) and isinstance(state, tuple) and len(state) >= 2 and state[1] in ("|", "<", "="):
        return
    if isinstance(obj, _Array) and obj.value is None and isinstance(state, tuple) and len(state) == 5:
        _, shape, dtype, fortran, raw = state
        obj.value = _array(path, pos, raw, dtype, shape, fortran)
        return
    raise FormatError(path, pos, "the pickle sets the state of an object evtk does not read")


def _plain(path, obj, done, busy):
    """``obj`` with the array stand-ins replaced by their arrays; a container met twice is converted once
    (``done``, by id), and one that contains itself is refused (``busy``)."""
    if isinstance(obj, _Array):
        if obj.value is None:
            raise FormatError(path, 0, "the pickle holds an array without its data")
        return obj.value
    if isinstance(obj, (_Global, _Dtype)):
        raise FormatError(path, 0, "the pickle holds a reference to code, not data")
    if not isinstance(obj, (dict, list, tuple)):
        return obj
    key = id(obj)
    if key in done:
        return done[key]
    if key in busy:
        raise FormatError(path, 0, "the pickle holds a container that contains itself")
    busy.add(key)
    if isinstance(obj, dict):
        out = {_plain(path, k, done, busy): _plain(path, v, done, busy) for k, v in obj.items()}
    else:
        out = type(obj)(_plain(path, v, done, busy) for v in obj)
    busy.discard(key)
    done[key] = out
    return out


def read_plain_pickle(path):
    """The value of a pickle made of plain data and numpy arrays, read without unpickling it.

    The opcodes are walked one by one (:func:`pickletools.genops`): numbers,
    strings, bytes, lists, tuples and dicts are built here, and an array is
    accepted only in the forms numpy writes (``_reconstruct`` with its state,
    or ``_frombuffer``) with an integer element type. Any other global, call,
    object, extension or persistent id is refused with the byte where it
    stands; nothing named by the file is imported or called.

    Parameters
    ----------
    path : str or os.PathLike
        The pickle file.

    Returns
    -------
    object
        The value: dicts, lists, tuples, str, bytes (Python 2 strings read as
        bytes), int, float, bool, None and numpy arrays.
    """
    import io

    path = os.fspath(path)
    try:
        size = os.path.getsize(path)
        require_memory(3 * size, f"reading the pickle {path}")  # its bytes, the strings in it and the arrays
        with open(path, "rb") as f:
            # from memory: a length field that lies makes a short read, never a read buffer of that length
            fh = io.BytesIO(f.read(size + 1))
    except OSError as exc:
        raise EvtkError(f"cannot read {path}: {exc.strerror or exc}") from None
    stack, marks, memo = [], [], {}
    stopped = False

    def bad(pos, what):
        return FormatError(path, pos, what)

    def pop_mark(pos):
        if not marks:
            raise bad(pos, "the pickle pops a mark it never set")
        m = marks.pop()
        items = stack[m:]
        del stack[m:]
        return items

    def top(pos, n=1):
        if len(stack) < n:
            raise bad(pos, "the pickle's stack runs empty")
        return stack[-n:]

    with fh:
        try:
            for op, arg, pos in pickletools.genops(fh):
                pos = int(pos or 0)
                name = op.name
                if name in ("PROTO", "FRAME"):
                    continue
                if name == "STOP":
                    if len(stack) != 1 or marks:
                        raise bad(pos, "the pickle ends with a malformed stack")
                    stopped = True
                    break
                if name in _STRING_OPS:
                    stack.append(arg.encode("latin-1"))
                elif name in _VALUE_OPS:
                    stack.append(arg)
                elif name == "BYTEARRAY8":
                    stack.append(bytearray(arg))
                elif name in ("NONE", "NEWTRUE", "NEWFALSE"):
                    stack.append({"NONE": None, "NEWTRUE": True, "NEWFALSE": False}[name])
                elif name == "MARK":
                    marks.append(len(stack))
                elif name == "EMPTY_DICT":
                    stack.append({})
                elif name == "EMPTY_LIST":
                    stack.append([])
                elif name == "EMPTY_TUPLE":
                    stack.append(())
                elif name in ("TUPLE1", "TUPLE2", "TUPLE3"):
                    n = int(name[-1])
                    items = top(pos, n)
                    del stack[-n:]
                    stack.append(tuple(items))
                elif name == "TUPLE":
                    stack.append(tuple(pop_mark(pos)))
                elif name == "LIST":
                    stack.append(pop_mark(pos))
                elif name == "DICT":
                    items = pop_mark(pos)
                    if len(items) % 2:
                        raise bad(pos, "a dict with a key and no value")
                    stack.append(dict(zip(items[::2], items[1::2])))
                elif name == "APPEND":
                    lst, value = top(pos, 2)
                    if not isinstance(lst, list):
                        raise bad(pos, "the pickle appends to something other than a list")
                    stack.pop()
                    lst.append(value)
                elif name == "APPENDS":
                    items = pop_mark(pos)
                    (lst,) = top(pos)
                    if not isinstance(lst, list):
                        raise bad(pos, "the pickle appends to something other than a list")
                    lst.extend(items)
                elif name == "SETITEM":
                    d, key, value = top(pos, 3)
                    if not isinstance(d, dict):
                        raise bad(pos, "the pickle sets an item of something other than a dict")
                    del stack[-2:]
                    d[key] = value
                elif name == "SETITEMS":
                    items = pop_mark(pos)
                    (d,) = top(pos)
                    if not isinstance(d, dict) or len(items) % 2:
                        raise bad(pos, "the pickle sets items of something other than a dict")
                    d.update(zip(items[::2], items[1::2]))
                elif name in ("PUT", "BINPUT", "LONG_BINPUT"):
                    memo[arg] = top(pos)[0]
                elif name == "MEMOIZE":
                    memo[len(memo)] = top(pos)[0]
                elif name in ("GET", "BINGET", "LONG_BINGET"):
                    if arg not in memo:
                        raise bad(pos, "the pickle refers to a value it never stored")
                    stack.append(memo[arg])
                elif name in ("GLOBAL", "STACK_GLOBAL"):
                    if name == "STACK_GLOBAL":
                        module, qual = top(pos, 2)
                        del stack[-2:]
                        if not isinstance(module, str) or not isinstance(qual, str):
                            raise bad(pos, "a global named by something other than text")
                        arg = f"{module} {qual}"
                    kind = _GLOBALS.get(arg)
                    if kind is None:
                        raise bad(pos, f"the pickle names {arg.replace(' ', '.')!r}, which evtk does not load "
                                       "(a pickle can run code; evtk reads only plain data and arrays)")
                    stack.append(_Global(kind))
                elif name == "REDUCE":
                    func, args = top(pos, 2)
                    del stack[-2:]
                    stack.append(_reduce(path, pos, func, args))
                elif name == "BUILD":
                    obj, state = top(pos, 2)
                    stack.pop()
                    _build(path, pos, obj, state)
                elif name == "POP":
                    top(pos)
                    stack.pop()
                elif name == "POP_MARK":
                    pop_mark(pos)
                elif name == "DUP":
                    stack.append(top(pos)[0])
                else:
                    raise bad(pos, f"the pickle uses {name}, which evtk does not read (it builds objects or "
                                   "runs code)")
        except FormatError:
            raise
        except (ValueError, TypeError, EOFError, OverflowError, MemoryError) as exc:
            raise FormatError(path, fh.tell(), f"not a pickle of plain data: {exc}") from None
    if not stopped:
        raise FormatError(path, 0, "the pickle has no STOP")
    try:
        return _plain(path, stack[0], {}, set())
    except RecursionError:
        raise FormatError(path, 0, "the pickle nests containers too deeply") from None
    except TypeError as exc:  # an array as a dict key
        raise FormatError(path, 0, f"not a pickle of plain data: {exc}") from None
