"""Data sets for the binary CNN, built from what is installed or on local disk (never downloaded).

* :func:`face_not_face`: scikit-image's bundled LFW subset (100 faces, 100
  non-faces); with ``data_dir`` holding Labeled Faces in the Wild
  (``lfw/<person>/*.jpg``) and CIFAR-10 (the binary version,
  ``cifar-10-batches-bin/data_batch_N.bin``, or the python version,
  ``cifar-10-batches-py/data_batch_N``, read without unpickling), the
  paper's balanced FNF set.
* :func:`letters_digits`: EMNIST from local IDX files (``data_dir`` with
  ``emnist-balanced-{train,test}-{images-idx3,labels-idx1}-ubyte[.gz]``);
  without them a synthetic glyph set rendered from the fonts matplotlib
  ships, marked ``synthetic`` in every report.

Images are downsampled to ``size`` x ``size`` by area and binarised at their
own mean to +-1 (int8), as the feature DMD shows them; labels are 0/1.
"""

from __future__ import annotations

import gzip
import os
import zlib
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .errors import EvtkError, FormatError
from .limits import require_memory

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = ["Dataset", "face_not_face", "letters_digits", "read_idx", "read_cifar_batch", "binarize_images",
           "load_dataset", "baselines"]


@dataclass
class Dataset:
    """A binary classification set of +-1 images.

    ``x_*`` are int8 (n, size, size) in {-1, +1}; ``y_*`` int8 labels in {0, 1}
    (``classes[1]`` is label 1); ``synthetic`` says the images are not real
    data; ``source`` says where they came from.

    Parameters
    ----------
    name : str
        The task (``"fnf"``, ``"letters-digits"``).
    x_train : numpy.ndarray
        int8 training images in {-1, +1}, shape ``(n, size, size)``.
    y_train : numpy.ndarray
        int8 training labels in {0, 1}, shape ``(n,)``.
    x_test : numpy.ndarray
        int8 test images, like ``x_train``.
    y_test : numpy.ndarray
        int8 test labels, like ``y_train``.
    classes : tuple of str
        Names of label 0 and label 1.
    source : str
        Where the images came from.
    synthetic : bool
        The images are not real data (rendered glyphs).
    """

    name: str
    x_train: np.ndarray
    y_train: np.ndarray
    x_test: np.ndarray
    y_test: np.ndarray
    classes: tuple
    source: str
    synthetic: bool = False

    def summary(self) -> dict:
        """What the set holds, for reports and JSON.

        Returns
        -------
        dict
            ``name``, ``train`` and ``test`` (sample counts), ``classes``, ``source``, ``synthetic`` and ``size``
            (the image shape).
        """
        return {"name": self.name, "train": int(len(self.y_train)), "test": int(len(self.y_test)),
                "classes": list(self.classes), "source": self.source, "synthetic": self.synthetic,
                "size": list(self.x_train.shape[1:])}


def binarize_images(images: npt.ArrayLike, size: int = 16, method: str = "mean") -> np.ndarray:
    """Area-downsample grey images to ``size`` x ``size`` and threshold each at its own mean (or Otsu's): +-1 int8.

    Parameters
    ----------
    images : array_like
        Grey images, shape ``(n, h, w)``, finite.
    size : int
        Side of the output images, pixels.
    method : {"mean", "otsu"}
        Each image's threshold: its mean, or Otsu's.

    Returns
    -------
    numpy.ndarray
        int8 in {-1, +1}, shape ``(n, size, size)``: +1 above the threshold.

    Raises
    ------
    EvtkError
        An empty or non-3-D stack, NaN or infinite values, or an unknown method.
    """
    from skimage.transform import resize

    imgs = np.asarray(images, dtype=np.float64)
    if imgs.ndim != 3 or imgs.shape[0] == 0:
        raise EvtkError(f"images must be a non-empty (n, h, w) stack, got shape {imgs.shape}")
    if not np.all(np.isfinite(imgs)):
        raise EvtkError("images hold NaN or infinite values")
    small = np.stack([resize(im, (size, size), anti_aliasing=True, preserve_range=True) for im in imgs])
    if method == "mean":
        thr = small.mean(axis=(1, 2), keepdims=True)
    elif method == "otsu":
        from skimage.filters import threshold_otsu

        thr = np.array([threshold_otsu(im) if np.ptp(im) > 0 else im.flat[0] for im in small])[:, None, None]
    else:
        raise EvtkError(f"binarisation method must be 'mean' or 'otsu', not {method!r}")
    return np.where(small > thr, 1, -1).astype(np.int8)


def _split(x: np.ndarray, y: np.ndarray, test_fraction: float,
           seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Stratified split: the same share of each class in the test set."""
    if not 0 < test_fraction < 1:
        raise EvtkError(f"test_fraction must be between 0 and 1, not {test_fraction}")
    rng = np.random.default_rng(seed)
    test = np.zeros(len(y), bool)
    for c in np.unique(y):
        idx = np.flatnonzero(y == c)
        rng.shuffle(idx)
        test[idx[: max(1, int(round(test_fraction * idx.size)))]] = True
    tr, te = np.flatnonzero(~test), np.flatnonzero(test)
    rng.shuffle(tr)
    rng.shuffle(te)
    return x[tr], y[tr], x[te], y[te]


# -- file formats -----------------------------------------------------------------------

def _open_maybe_gzip(path):
    with open(path, "rb") as fh:
        head = fh.read(2)
    return gzip.open(path, "rb") if head == b"\x1f\x8b" else open(path, "rb")


_IDX_TYPES: dict[int, npt.DTypeLike] = {0x08: np.uint8, 0x09: np.int8, 0x0B: ">i2", 0x0C: ">i4", 0x0D: ">f4", 0x0E: ">f8"}


def read_idx(path: str | os.PathLike[str]) -> np.ndarray:
    """An IDX file (the MNIST/EMNIST format, optionally gzip-compressed) as a numpy array.

    The header's shape is checked against the memory budget before the body
    is read (or inflated), and exactly that many bytes are read: a short body
    or bytes after it are refused.

    Parameters
    ----------
    path : str or os.PathLike
        The IDX file, plain or gzip.

    Returns
    -------
    numpy.ndarray
        The array in native byte order, of the shape the header declares.

    Raises
    ------
    FormatError
        A bad magic number, a truncated header or body, bytes after the body, or a file that cannot be read
        (naming the file and byte offset).
    EvtkError
        More memory than the budget.
    """
    path = os.fspath(path)
    try:
        with _open_maybe_gzip(path) as fh:
            magic = fh.read(4)
            if len(magic) < 4 or magic[0] != 0 or magic[1] != 0 or magic[2] not in _IDX_TYPES or magic[3] == 0:
                raise FormatError(path, 0, "not an IDX file (bad magic number)")
            ndim = magic[3]
            dims = fh.read(4 * ndim)
            if len(dims) < 4 * ndim:
                raise FormatError(path, 4, "IDX header is truncated")
            shape = tuple(int.from_bytes(dims[4 * i: 4 * i + 4], "big") for i in range(ndim))
            dtype = np.dtype(_IDX_TYPES[magic[2]])
            need = int(np.prod(shape, dtype=object)) * dtype.itemsize
            start = 4 + 4 * ndim
            require_memory(2 * need, f"the IDX file {path} ({'x'.join(map(str, shape))} values)")
            body = fh.read(need)
            if len(body) < need:
                raise FormatError(path, start + len(body), f"IDX data is truncated: {len(body)} of {need} bytes")
            if fh.read(1):
                raise FormatError(path, start + need, f"bytes follow the {need} bytes of data the IDX header declares")
    except FormatError:
        raise
    except (OSError, EOFError, zlib.error) as exc:  # (gzip.BadGzipFile is an OSError)
        raise FormatError(path, 0, f"cannot read IDX file: {exc}") from None
    return np.frombuffer(body, dtype=dtype).reshape(shape).astype(dtype.newbyteorder("="))


_CIFAR_RECORD = 1 + 3072  # the binary version: a label byte, then 32x32 red, green and blue planes
_CIFAR_KEYS = {"batch_label", "labels", "data", "filenames"}


def read_cifar_batch(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """One CIFAR-10 batch, binary (``data_batch_N.bin``) or python version (``data_batch_N``), as grey images.

    The binary version is records of one label byte and 3072 image bytes.
    The python version is a pickle: it is walked opcode by opcode and
    accepted only with the structure CIFAR-10's batches have (a dict of
    ``data``, a uint8 array of 3072 columns, and ``labels``, a list of whole
    numbers); it is never unpickled, so a crafted file runs no code.

    Parameters
    ----------
    path : str or os.PathLike
        The batch file.

    Returns
    -------
    grey : numpy.ndarray
        (n, 32, 32) float64 in [0, 1] (luminance of the colour image).
    labels : numpy.ndarray
        (n,) int64.

    Raises
    ------
    FormatError
        A file that cannot be read, is not whole records, holds a label above 9, or a pickle of another
        structure (naming the file and byte offset).
    EvtkError
        More memory than the budget.
    """
    path = os.fspath(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(2)
        size = os.path.getsize(path)
    except OSError as exc:
        raise FormatError(path, 0, f"cannot read CIFAR-10 batch: {exc.strerror or exc}") from None
    if head[:1] and head[0] > 9:  # not a label byte: a pickle, the python version
        data, labels = _cifar_python(path)
    else:
        if size == 0 or size % _CIFAR_RECORD:
            raise FormatError(path, size - size % _CIFAR_RECORD,
                              f"not a CIFAR-10 binary batch: {size:,} bytes is not a whole number of "
                              f"{_CIFAR_RECORD}-byte records")
        require_memory(size, f"the CIFAR-10 batch {path}")
        raw = np.fromfile(path, dtype=np.uint8).reshape(-1, _CIFAR_RECORD)
        labels, data = raw[:, 0].astype(np.int64), raw[:, 1:]
        bad = np.flatnonzero(labels > 9)
        if bad.size:
            raise FormatError(path, int(bad[0]) * _CIFAR_RECORD, f"label {labels[bad[0]]} is not a CIFAR-10 class")
    require_memory(len(data) * 3072 * 8 * 2, f"the images of {path}")
    rgb = data.reshape(-1, 3, 32, 32).astype(np.float64) / 255.0
    grey = 0.2125 * rgb[:, 0] + 0.7154 * rgb[:, 1] + 0.0721 * rgb[:, 2]
    return grey, labels


def _cifar_python(path):
    """``data`` and ``labels`` of CIFAR-10's python version, read without unpickling."""
    from ._loaders import read_plain_pickle

    d = read_plain_pickle(path)
    if isinstance(d, dict):
        d = {k.decode("latin-1") if isinstance(k, bytes) else k: v for k, v in d.items()}
    if not isinstance(d, dict) or not {"data", "labels"} <= set(d) or not set(d) <= _CIFAR_KEYS:
        raise FormatError(path, 0, "not a CIFAR-10 python batch (a dict of data and labels); the binary version "
                                   "(data_batch_N.bin) reads without a pickle")
    data, labels = d["data"], d["labels"]
    if not isinstance(data, np.ndarray) or data.ndim != 2 or data.shape[1] != 3072:
        raise FormatError(path, 0, "CIFAR-10 batch data is not an array of 3072 bytes per image")
    if not isinstance(labels, list) or not all(type(v) is int and 0 <= v <= 9 for v in labels) \
            or len(labels) != len(data):
        raise FormatError(path, 0, f"CIFAR-10 batch labels are not {len(data)} classes 0-9")
    return data, np.asarray(labels, dtype=np.int64)


# -- face / not face ---------------------------------------------------------------------

def face_not_face(seed: int = 0, test_fraction: float = 0.3, data_dir: str | os.PathLike[str] | None = None,
                  size: int = 16, n_per_class: int | None = None) -> Dataset:
    """Faces against non-faces, binarised to ``size`` x ``size``.

    Without ``data_dir``: scikit-image's LFW subset (100 and 100). With it:
    ``n_per_class`` (default 1000) LFW faces, centre-cropped, against as many
    CIFAR-10 images, all grey.

    Parameters
    ----------
    seed : int
        Seed of the sampling and of the stratified split.
    test_fraction : float
        Share of each class in the test set, in (0, 1).
    data_dir : str, os.PathLike or None
        Folder holding ``lfw/`` and a CIFAR-10 batches folder; None uses the bundled subset.
    size : int
        Side of the images, pixels.
    n_per_class : int or None
        Images per class from ``data_dir`` (None: 1000); ignored without it.

    Returns
    -------
    Dataset
        ``"fnf"``, faces labelled 1.

    Raises
    ------
    EvtkError
        Missing LFW or CIFAR-10 files, a bad ``test_fraction``, or more memory than the budget.
    FormatError
        A damaged image or batch.
    """
    if data_dir is None:
        from skimage import data

        imgs = data.lfw_subset()
        x = binarize_images(imgs, size)
        y = np.r_[np.ones(100, np.int8), np.zeros(100, np.int8)]
        source = "scikit-image lfw_subset (100 faces, 100 non-faces)"
    else:
        n = int(n_per_class or 1000)
        faces = _lfw_faces(os.path.join(data_dir, "lfw"), n, seed)
        others = _cifar_images(data_dir, n, seed)
        x = np.concatenate([binarize_images(faces, size), binarize_images(others, size)])
        y = np.r_[np.ones(len(faces), np.int8), np.zeros(len(others), np.int8)]
        source = f"LFW ({len(faces)} faces) and CIFAR-10 ({len(others)} images) from {data_dir}"
    return Dataset("fnf", *_split(x, y, test_fraction, seed), ("not face", "face"), source)


def _lfw_faces(root, n, seed):
    from skimage.color import rgb2gray

    from ._loaders import read_image

    if not os.path.isdir(root):
        raise EvtkError(f"no LFW folder at {root} (expected lfw/<person>/*.jpg)")
    files = sorted(os.path.join(d, f) for d, _, fs in os.walk(root) for f in fs if f.lower().endswith(".jpg"))
    if not files:
        raise EvtkError(f"no .jpg images under {root}")
    rng = np.random.default_rng(seed)
    pick = rng.permutation(len(files))[:n]
    out = []
    held = 0
    for i in pick:
        im = read_image(files[i], "LFW image")
        held += im.size * 8
        require_memory(held, f"{len(out) + 1} LFW images")
        if im.ndim == 3:
            im = im[..., :3]
        im = rgb2gray(im) if im.ndim == 3 else im.astype(np.float64)
        h, w = im.shape
        c = min(h, w) // 2  # the face sits in the middle half of an LFW picture
        out.append(im[h // 2 - c // 2: h // 2 + c // 2, w // 2 - c // 2: w // 2 + c // 2])
    side = min(min(o.shape) for o in out)
    from skimage.transform import resize

    return np.stack([resize(o, (side, side), anti_aliasing=True) for o in out])


def _cifar_images(data_dir, n, seed):
    files = []
    for folder in ("cifar-10-batches-bin", "cifar-10-batches-py"):  # the binary version first
        root = os.path.join(data_dir, folder)
        if os.path.isdir(root):
            files = sorted(os.path.join(root, f) for f in os.listdir(root) if f.startswith("data_batch"))
        if files:
            break
    if not files:
        raise EvtkError(f"no CIFAR-10 batches (cifar-10-batches-bin/data_batch_N.bin or "
                        f"cifar-10-batches-py/data_batch_N) in {data_dir}")
    batches, held = [], 0
    for f in files:
        batches.append(read_cifar_batch(f)[0])
        held += batches[-1].nbytes
        require_memory(2 * held, f"{len(batches)} CIFAR-10 batches")
    imgs = np.concatenate(batches)
    rng = np.random.default_rng(seed + 1)
    return imgs[rng.permutation(len(imgs))[:n]]


# -- letters / digits --------------------------------------------------------------------

def letters_digits(seed: int = 0, test_fraction: float = 0.3, data_dir: str | os.PathLike[str] | None = None,
                   size: int = 16, n_per_class: int = 1000) -> Dataset:
    """Letters (label 1) against digits (label 0), ``n_per_class`` of each.

    With ``data_dir``: EMNIST "balanced" IDX files (digits are classes 0-9,
    letters 10-46), drawn from the training file. Without: a synthetic set
    rendered from matplotlib's bundled fonts.

    Parameters
    ----------
    seed : int
        Seed of the sampling, the rendering and the split.
    test_fraction : float
        Share of each class in the test set, in (0, 1).
    data_dir : str, os.PathLike or None
        Folder holding the EMNIST balanced IDX files; None renders synthetic glyphs.
    size : int
        Side of the images, pixels.
    n_per_class : int
        Images per class.

    Returns
    -------
    Dataset
        ``"letters-digits"``, letters labelled 1; ``synthetic`` when rendered.

    Raises
    ------
    EvtkError
        No EMNIST files in ``data_dir``, a bad ``test_fraction``, or more memory than the budget.
    FormatError
        A damaged IDX file.
    """
    if data_dir is not None:
        imgs, labels = _emnist(data_dir)
        rng = np.random.default_rng(seed)
        digits = rng.permutation(np.flatnonzero(labels < 10))[:n_per_class]
        letters = rng.permutation(np.flatnonzero(labels >= 10))[:n_per_class]
        x = binarize_images(imgs[np.r_[digits, letters]].astype(np.float64), size, method="otsu")
        y = np.r_[np.zeros(len(digits), np.int8), np.ones(len(letters), np.int8)]
        return Dataset("letters-digits", *_split(x, y, test_fraction, seed), ("digit", "letter"),
                       f"EMNIST balanced from {data_dir}")
    x, y = synthetic_glyphs(n_per_class, size, seed)
    return Dataset("letters-digits", *_split(x, y, test_fraction, seed), ("digit", "letter"),
                   "synthetic glyphs rendered from matplotlib's bundled fonts (not EMNIST)", synthetic=True)


def _emnist(data_dir):
    for split in ("train", "test"):
        base = os.path.join(data_dir, f"emnist-balanced-{split}")
        for ext in ("", ".gz"):
            img, lab = f"{base}-images-idx3-ubyte{ext}", f"{base}-labels-idx1-ubyte{ext}"
            if os.path.exists(img) and os.path.exists(lab):
                x, y = read_idx(img), read_idx(lab)
                if x.ndim != 3 or y.ndim != 1 or len(x) != len(y):
                    raise FormatError(img, 0, f"images {x.shape} and labels {y.shape} do not match")
                return np.transpose(x, (0, 2, 1)), y.astype(np.int64)  # EMNIST stores images transposed
    raise EvtkError(f"no EMNIST balanced IDX files in {data_dir}")


_GLYPH_FONTS = ("DejaVuSans.ttf", "DejaVuSans-Bold.ttf", "DejaVuSerif.ttf", "DejaVuSansMono.ttf",
                "DejaVuSans-Oblique.ttf", "DejaVuSerif-Bold.ttf")


def _glyph_bitmaps(chars, res=48):
    """High-resolution bitmaps of every (char, font), rendered once with matplotlib's Agg."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.font_manager import FontProperties

    font_dir = os.path.join(os.path.dirname(matplotlib.__file__), "mpl-data", "fonts", "ttf")
    out = {}
    for font in _GLYPH_FONTS:
        prop = FontProperties(fname=os.path.join(font_dir, font), size=res * 1.4)
        for ch in chars:
            fig = Figure(figsize=(1, 1), dpi=res)
            canvas = FigureCanvasAgg(fig)
            fig.text(0.5, 0.5, ch, fontproperties=prop, ha="center", va="center")
            canvas.draw()
            rgba = np.asarray(canvas.buffer_rgba(), dtype=np.float64)
            out[(ch, font)] = 1.0 - rgba[..., :3].mean(axis=2) / 255.0  # ink = 1
    return out


def synthetic_glyphs(n_per_class: int, size: int = 16, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Letters and digits drawn alike: random font, affine jitter, stroke noise; +-1 images and labels (letter = 1).

    Parameters
    ----------
    n_per_class : int
        Images of each class.
    size : int
        Side of the images, pixels.
    seed : int
        Seed of the fonts, glyphs, jitter and noise.

    Returns
    -------
    images : numpy.ndarray
        int8 in {-1, +1}, shape ``(2 * n_per_class, size, size)``: the digits first.
    labels : numpy.ndarray
        int8, 0 for a digit and 1 for a letter.
    """
    from skimage.transform import AffineTransform, warp

    letters = "ABCDEFGHJKLMNPQRSTUVWXYZabdefghnqrt"
    digits = "0123456789"
    bitmaps = _glyph_bitmaps(letters + digits)
    rng = np.random.default_rng(seed)
    imgs, labels = [], []
    for label, chars in ((0, digits), (1, letters)):
        for _ in range(int(n_per_class)):
            ch = chars[rng.integers(len(chars))]
            bm = bitmaps[(ch, _GLYPH_FONTS[rng.integers(len(_GLYPH_FONTS))])]
            c = np.array(bm.shape[::-1]) / 2.0
            t = (AffineTransform(translation=-c)
                 + AffineTransform(scale=rng.uniform(0.8, 1.15, 2), rotation=rng.normal(0, 0.12),
                                   shear=rng.normal(0, 0.12))
                 + AffineTransform(translation=c + rng.normal(0, 2.0, 2)))
            im = warp(bm, t.inverse, order=1, mode="constant")
            im = im + rng.normal(0, 0.1, im.shape)  # stroke noise
            imgs.append(im)
            labels.append(label)
    return binarize_images(np.stack(imgs), size, method="otsu"), np.asarray(labels, np.int8)


def load_dataset(task: str, seed: int = 0, data_dir: str | os.PathLike[str] | None = None,
                 test_fraction: float = 0.3, n_per_class: int | None = None) -> Dataset:
    """``"fnf"`` or ``"letters-digits"``; ``n_per_class`` None: the task's default.

    Parameters
    ----------
    task : {"fnf", "letters-digits"}
        Which set (:func:`face_not_face` or :func:`letters_digits`).
    seed : int
        Seed of the sampling and the split.
    data_dir : str, os.PathLike or None
        Local data (see the two functions); None uses what is installed.
    test_fraction : float
        Share of each class in the test set.
    n_per_class : int or None
        Samples per class (at least 2); None takes the task's default.

    Returns
    -------
    Dataset
        The binarised 16x16 set.

    Raises
    ------
    EvtkError
        An unknown task, fewer than 2 samples per class, or a sample count for the bundled LFW subset.
    """
    if n_per_class is not None and int(n_per_class) < 2:
        raise EvtkError(f"need at least 2 samples per class, not {n_per_class}")
    if task == "fnf":
        if n_per_class is not None and data_dir is None:
            raise EvtkError("the bundled LFW subset has 100 faces and 100 non-faces: choosing the number of "
                            "samples needs a data directory")
        return face_not_face(seed, test_fraction, data_dir, n_per_class=n_per_class)
    if task == "letters-digits":
        return letters_digits(seed, test_fraction, data_dir, n_per_class=1000 if n_per_class is None else n_per_class)
    raise EvtkError(f"task must be 'fnf' or 'letters-digits', not {task!r}")


def baselines(data: Dataset, l2: float = 1e-2, iterations: int = 200) -> dict:
    """Test accuracy of two plain classifiers on ``data``'s own split: the floor a binary CNN should clear.

    ``nearest_centroid``: the label of the closer class mean (Euclidean, on
    the +-1 pixels). ``logistic_regression``: L2-regularised (``l2`` on the
    weights, not the bias) logistic regression on the pixels, fitted by
    Newton's method (``iterations`` at most; it converges in a few dozen on
    these sizes). Both see exactly the train and test images the CNN sees.

    Parameters
    ----------
    data : Dataset
        The set, with both classes in its training split.
    l2 : float
        Regularisation of the logistic regression's weights (times the training samples).
    iterations : int
        Most Newton steps.

    Returns
    -------
    dict
        ``nearest_centroid`` and ``logistic_regression`` test accuracies in [0, 1], and ``test_images``.

    Raises
    ------
    EvtkError
        When the training split holds one class only.
    """
    xtr = data.x_train.reshape(len(data.x_train), -1).astype(np.float64)
    xte = data.x_test.reshape(len(data.x_test), -1).astype(np.float64)
    ytr = data.y_train.astype(np.float64)
    yte = data.y_test.astype(np.int64)
    if len(np.unique(ytr)) < 2:
        raise EvtkError("the training split holds one class only: no baseline can be fitted")
    c0, c1 = xtr[ytr == 0].mean(axis=0), xtr[ytr == 1].mean(axis=0)
    nc = (((xte - c1) ** 2).sum(axis=1) < ((xte - c0) ** 2).sum(axis=1)).astype(np.int64)
    a = np.hstack([xtr, np.ones((len(xtr), 1))])
    w = np.zeros(a.shape[1])
    reg = np.full(a.shape[1], float(l2) * len(xtr))
    reg[-1] = 0.0
    for _ in range(int(iterations)):
        z = np.clip(a @ w, -40, 40)
        prob = 1.0 / (1.0 + np.exp(-z))
        grad = a.T @ (prob - ytr) + reg * w
        hess = (a * (prob * (1 - prob))[:, None]).T @ a + np.diag(reg + 1e-9)
        step = np.linalg.solve(hess, grad)
        w -= step
        if np.max(np.abs(step)) < 1e-8:
            break
    lr = ((np.hstack([xte, np.ones((len(xte), 1))]) @ w) > 0).astype(np.int64)
    return {"nearest_centroid": float(np.mean(nc == yte)), "logistic_regression": float(np.mean(lr == yte)),
            "test_images": int(len(yte))}

