"""Reading an image file into its array without torch: the command line's parent process decodes with it while
its workers start, and :mod:`svs_torch.data.formats` reads every image through it.

:func:`read_image_array` decodes with OpenCV from the file's bytes. :data:`PRELOADED` holds arrays another
process decoded the same way (``svs-depth estimate --pairs`` decodes the first pairs in its parent while the
workers' server imports torch, and sends them with each batch): a file found there is not read again.
"""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
from pathlib import Path

import cv2
import numpy as np

from .errors import InputError
from .files import STDERR_LOCK, check_path_given, display_path, path_kind

__all__ = ["JPEG_GRAY_DECODE", "MAX_DECODED_PIXELS", "PRELOADED", "check_file", "damaged_jpeg", "declared_file_size",
           "declared_pixels", "declared_size", "decode_collecting", "preload_key", "read_image_array",
           "turned_note"]

#: Arrays decoded elsewhere by :func:`read_image_array`, by :func:`preload_key` of their file: each is returned for
#: every read of that file until its owner clears the dict (an ``estimate --pairs`` worker, after each batch).
PRELOADED: dict[str, np.ndarray] = {}

#: A JPEG file's first bytes (start of image, then a marker), and how ``gray`` (and the live stream,
#: :func:`svs_torch.capture.stereo.decode_frame`) decodes one: its luma, turned by its EXIF orientation tag as
#: ``cv2.imread(path, cv2.IMREAD_GRAYSCALE)`` and every viewer turn it. Why: a phone stores a portrait photo's
#: pixels on their side with a tag; ignored, a pair's baseline ran along its columns, and estimate ranged Teddy at
#: 0.87 m or 11.6 m instead of 1.25 m with status OK (an audit). The SVS's frames carry no tag.
_JPEG_START = b"\xff\xd8\xff"
_JPEG_END = b"\xff\xd9"
JPEG_GRAY_DECODE = cv2.IMREAD_GRAYSCALE


def preload_key(path: str | Path) -> str:
    """The key of ``path`` in :data:`PRELOADED`: the file it opens, links resolved. Not its absolute path: that
    drops ``lnk/..`` by its letters, and ``lnk/../L.png`` (the file beside ``lnk``'s target) and ``L.png`` had one
    key, so ``estimate --pairs`` in workers ranged one pair on the other's images (an audit)."""
    return os.path.realpath(os.fspath(path))


def check_file(path: str | Path, name: str) -> Path:
    """``path`` as a :class:`Path`; raises :class:`InputError` naming ``name`` when it is not an existing file."""
    check_path_given(path, name)
    kind = path_kind(path, name)
    if kind == "missing" and os.fspath(path) == "-":  # the Unix habit; was "file not found: -" (an audit)
        raise InputError(f"{name}: '-' (standard input) is not read: expected an image file name")
    if kind == "missing":
        raise InputError(f"{name}: file not found: {display_path(path)}")
    if kind != "file":
        raise InputError(f"{name}: expected a file, got a directory or special file: {display_path(path)}")
    return Path(path)


# OpenCV's log prefix ("[ERROR:0@2.476] global grfmt_tiff.cpp:117 ") and libtiff's tag, cut from decoder messages.
_NATIVE_PREFIX = re.compile(r"^\[\s*\w+:\d+@[\d.]+\]\s*(global\s+\S+\s+)?(\w+\s+)?(TIFF_Error\s+)?")


@contextlib.contextmanager
def _native_stderr_collected(lines: list[str]):
    """Collect into ``lines`` what C decoders (libpng, libjpeg, libtiff, OpenCV's logger) write to file
    descriptor 2 meanwhile: a corrupt file then gives one :class:`InputError` line, not their noise.

    Python's ``sys.stderr`` is untouched, but anything another thread writes to descriptor 2 in the window
    (a decode, milliseconds) lands in ``lines`` too, but for the command line's own lines, which wait for
    :data:`~svs_torch.core.files.STDERR_LOCK`; the lock also keeps two windows from interleaving.
    """
    with STDERR_LOCK:
        try:
            saved = os.dup(2)
        except OSError:  # no descriptor 2 (a daemon): nothing to keep quiet
            yield
            return
        try:
            with tempfile.TemporaryFile() as sink:
                os.dup2(sink.fileno(), 2)
                try:
                    yield
                finally:
                    os.dup2(saved, 2)
                sink.seek(0)
                text = sink.read().decode("utf-8", "replace")
        finally:
            os.close(saved)
    # OpenCV continues a message on lines starting with "> " (e.g. "> Unsupported number of channels:").
    for line in text.splitlines():
        if line.startswith(">") and lines:
            lines[-1] = f"{lines[-1]} {line.lstrip('> ').strip()}".strip()
        elif line.strip():
            lines.append(_decoder_message(line))


def _decoder_message(line: str) -> str:
    """The gist of a decoder's line: no log prefix, no ``OpenCV(5.0.0) /path/file.cpp:59: error: (-2:...)``."""
    line = _NATIVE_PREFIX.sub("", line.strip())
    line = re.sub(r"^imdecode_\(''\):\s*", "", line)
    line = re.sub(r"OpenCV\([^)]*\) \S+: error: \([^)]*\)\s*", "", line)
    return re.sub(r"\s*in function '[^']*'$", "", line).strip()


#: The most pixels an image file may declare (8192 x 8192): a 30000 x 30000 PNG of zeros is a 1 MB file that
#: would decode into 900 MB, then be refused for its size anyway.
MAX_DECODED_PIXELS = 1 << 26
#: libjpeg's warnings for a JPEG whose image data is damaged (lost or wrong entropy-coded bytes): it still returns an
#: image, with the damaged blocks filled. Not "N extraneous bytes before marker", which some cameras write and which
#: costs no pixel.
_DAMAGED_JPEG = re.compile(r"Corrupt JPEG data: (?!\d+ extraneous bytes)|Premature end of JPEG file")
_JPEG_FRAME_MARKERS = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def declared_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG or JPEG header, read before decoding; None for other formats or a header
    that does not say (OpenCV then decides). A JPEG's frame header is found by walking its segments from the
    start, however much metadata comes first (a 70 kB colour profile once put it past what was read)."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24:
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if data[:2] != b"\xff\xd8":
        return None
    position = 2
    while position + 9 <= len(data) and data[position] == 0xFF:
        marker = data[position + 1]
        if marker in _JPEG_FRAME_MARKERS:  # SOFn: length, precision, height, width
            return (int.from_bytes(data[position + 7:position + 9], "big"),
                    int.from_bytes(data[position + 5:position + 7], "big"))
        if marker == 0xDA:  # start of scan: no frame header before it
            return None
        position += 2 + int.from_bytes(data[position + 2:position + 4], "big")
    return None


def declared_file_size(path: str | Path) -> tuple[int, int] | None:
    """(width, height) that the PNG or JPEG header of the regular file ``path`` declares, read before decoding;
    None where the header does not say, or ``path`` is no regular file or cannot be read (a FIFO's read would
    block; the loader then says why)."""
    if not os.path.isfile(path):
        return None
    try:
        with open(path, "rb") as file:
            return declared_size(file.read(1 << 20))  # a JPEG's frame header follows its metadata, under 1 MB
    except OSError:
        return None


def turned_note(path: str | Path, size_wh: tuple[int, int]) -> str:
    """``", turned upright by its EXIF orientation from the 640x480 it stores"`` where the PNG or JPEG file ``path``
    stores its pixels on their side and was read as ``size_wh``, else ``""``. Why: a pair whose left photo carries
    an Orientation tag was refused as "expected the size of left 480x640", a size that neither file's header nor
    an image tool's listing of it shows (an audit)."""
    stored = declared_file_size(path)
    if stored is None or stored[0] == stored[1] or stored != tuple(size_wh)[::-1]:
        return ""
    return f", turned upright by its EXIF orientation from the {stored[0]}x{stored[1]} it stores"


def declared_pixels(data: bytes) -> tuple[int, str] | None:
    """How many pixels an image file declares, read from its header before decoding, and how to say it
    (``"30000x30000"``): PNG and JPEG by :func:`declared_size`, every other format Pillow reads the header of
    (TIFF, WebP, BMP, GIF, PNM, JPEG 2000, ...; Pillow comes with matplotlib); None where no header says.

    Why every format: a 1.4 MB deflated TIFF of 30000 x 30000 zeros decoded into 6.7 GB before the size was
    refused, and as one line of a pair list it ended the whole run with a MemoryError."""
    size = declared_size(data)
    if size is not None:
        return size[0] * size[1], f"{size[0]}x{size[1]}"
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover -- matplotlib requires Pillow
        return None
    import io
    import warnings

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # Pillow's DecompressionBombWarning: the caller decides
            with Image.open(io.BytesIO(data)) as image:  # reads the header only
                width, height = image.size
    except Image.DecompressionBombError as error:  # over twice Pillow's own limit: its message has the count
        counted = re.search(r"\((\d+) pixels\)", str(error))
        return None if counted is None else (int(counted.group(1)), f"{int(counted.group(1)):,}")
    except Exception:  # noqa: BLE001 -- a header Pillow cannot read: OpenCV decides, and says why
        return None
    return width * height, f"{width}x{height}"


def decode_collecting(data: np.ndarray, flags: int) -> tuple[np.ndarray | None, list[str]]:
    """``cv2.imdecode(data, flags)`` (None for bytes it cannot decode) and what the decoders said meanwhile, one
    message a line (:func:`_native_stderr_collected`), instead of their lines on stderr."""
    complaints: list[str] = []
    array = None
    if data.size:
        with _native_stderr_collected(complaints):
            # imdecode returns None (it does not raise) for bytes it cannot decode, e.g. text renamed .png, and
            # raises cv2.error for e.g. a header announcing more pixels than OpenCV's limit.
            try:
                array = cv2.imdecode(data, flags)
            except cv2.error as error:
                complaints.append(_decoder_message(str(error).strip().splitlines()[-1]))
    return array, complaints


def damaged_jpeg(complaints: list[str]) -> str | None:
    """libjpeg's complaint, among a decode's ``complaints``, that the JPEG's image data was damaged (shortened to
    a line), or None: such a JPEG still decodes, its lost blocks filled with gray."""
    damaged = next((line for line in complaints if _DAMAGED_JPEG.search(line)), None)
    return None if damaged is None else ' '.join(damaged.split())[:120]


#: How to turn an array stored under each EXIF Orientation tag (2-8) upright, as viewers and cv2.imread do.
_UPRIGHT = {2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1],
            5: lambda a: a.swapaxes(0, 1), 6: lambda a: np.rot90(a, -1), 7: lambda a: a[::-1, ::-1].swapaxes(0, 1),
            8: lambda a: np.rot90(a, 1)}


def _turned_upright(array: np.ndarray, raw: bytes) -> np.ndarray:
    """A PNG's or WebP's ``array`` turned by the file's EXIF Orientation tag: ``IMREAD_UNCHANGED`` ignores it there
    (a JPEG's gray decode and a TIFF's turn it). Why: a phone's portrait photo converted to PNG keeps its pixels on
    their side with the tag, and estimate ranged such a Teddy pair at 0.93 m instead of 1.24 m, status OK (an
    audit). Pillow reads the tag, only for a file whose bytes hold an EXIF chunk's name."""
    png, webp = raw[:8] == b"\x89PNG\r\n\x1a\n", raw[:4] == b"RIFF" and raw[8:12] == b"WEBP"
    if not ((png and b"eXIf" in raw) or (webp and b"EXIF" in raw)):
        return array
    import io

    from PIL import Image

    try:
        with Image.open(io.BytesIO(raw)) as image:
            exif = image.getexif()
    except Exception:  # noqa: BLE001 -- a header Pillow cannot read: as OpenCV decoded it
        return array
    turn = _UPRIGHT.get(exif.get(0x0112))
    return array if turn is None else np.ascontiguousarray(turn(array))


def _heif(raw: bytes) -> bool:
    """The file's bytes are a HEIF image's (an ISO media 'ftyp' box naming a HEIF brand)."""
    return raw[4:8] == b"ftyp" and raw[8:12] in (b"heic", b"heix", b"hevc", b"hevx", b"heim", b"heis", b"mif1",
                                                 b"msf1")


def read_image_array(path: str | Path, name: str, gray: bool = False) -> np.ndarray:
    """Read an image unchanged (bit depth and channels kept) with OpenCV, or raise :class:`InputError`.

    ``gray``: a JPEG file is decoded to its gray levels at once (OpenCV's ``IMREAD_GRAYSCALE``: the luma the
    JPEG stores, as ``cv2.imread(path, cv2.IMREAD_GRAYSCALE)`` reads it and as ``guide`` decodes the SVS's frames,
    :func:`svs_torch.capture.stereo.decode_frame`), not to colour first: a colour JPEG's chroma is stored at half
    width (the SVS's 4:2:2), and BGR upsampled from it and weighted back to gray moves 8 % of a street frame's
    pixels by up to 18 levels, so ``estimate`` on a frame ``capture`` saved would not see what ``guide`` saw.
    With ``gray`` a PNG or WebP is turned by its EXIF orientation too (:func:`_turned_upright`). Other formats, and
    JPEGs without ``gray``, come unchanged.

    The file's bytes are read by Python and decoded from memory: any file name works, a truncated file is
    refused (reading from a file, OpenCV would fill a truncated JPEG's missing rows with gray), and the
    decoders' own complaints become the reason of the error instead of lines of their own on stderr. A file in
    :data:`PRELOADED` is not read again: its array is returned as it is (callers do not write to it).
    """
    if PRELOADED:
        preloaded = PRELOADED.get(preload_key(path))
        if preloaded is not None:
            return preloaded
    path = check_file(path, name)
    try:
        raw = path.read_bytes()
    except OSError as error:
        raise InputError(f"{name}: cannot read {display_path(path)}: {error.strerror or error}") from None
    data = np.frombuffer(raw, np.uint8)
    declared = declared_pixels(raw)
    if declared is not None and declared[0] > MAX_DECODED_PIXELS:
        raise InputError(f"{name}: the file declares {declared[1]} pixels, more than the "
                         f"{MAX_DECODED_PIXELS // 2**20} megapixels read: {display_path(path)}")
    jpeg = data[:3].tobytes() == _JPEG_START
    flags = JPEG_GRAY_DECODE if gray and jpeg else cv2.IMREAD_UNCHANGED
    array, complaints = decode_collecting(data, flags)
    if array is None and jpeg and data[-2:].tobytes() != _JPEG_END:
        # Without its end marker imdecode returns None and libjpeg says nothing, where imread reads a JPEG whole
        # but for the marker: with it, such a file is read, and one cut short is a damaged JPEG with libjpeg's
        # reason (both were "not a readable image file", with none; an audit).
        array, complaints = decode_collecting(np.concatenate([data, np.frombuffer(_JPEG_END, np.uint8)]), flags)
    reason = f": {' '.join(complaints[0].split())[:160]}" if complaints else ""
    if array is None:
        kind = "an empty file" if not data.size else "not a readable image file"
        if _heif(raw):  # a phone's photo (an iPhone's default): its format named and what to do (an audit)
            raise InputError(f"{name}: a HEIF/HEIC photo, which OpenCV does not decode: save it as JPEG or PNG: "
                             f"{display_path(path)}")
        raise InputError(f"{name}: {kind} (OpenCV could not decode it{reason}): {display_path(path)}")
    damaged = damaged_jpeg(complaints)
    if damaged is not None:  # libjpeg decoded what it could and filled the rest: an image, but not the scene's
        raise InputError(f"{name}: a damaged JPEG (libjpeg: {damaged}): {display_path(path)}")
    if gray and not jpeg:
        array = _turned_upright(array, raw)
    # Otherwise a file that decodes is taken as it is: what the decoders said about it (an unknown TIFF tag, a PNG
    # colour profile, bytes between a JPEG's segments) is not worth a line.
    return array
