"""Volume file headers checked before a reader trusts them (NRRD, NIfTI-1/2).

ITK, under SimpleITK and 3D Slicer's MRML, reads lying headers without a word
(measured with SimpleITK 2.4 / ITK 5.4, ``Testing/Python/test_volume_headers.py``):

- NIfTI: a NaN, zero or negative ``pixdim`` becomes spacing 1 or a flipped axis,
  a NaN quaternion, a skewed or mismatched ``sform`` are ignored for the other
  transform ("unexpected scales in sform" on stderr, then exit 0);
- NRRD: ``spacings: nan`` becomes 1, a skewed ``space directions`` is
  normalised into a non-orthonormal direction;
- both: data beyond what the header declares (``sizes`` x ``type``; ``dim`` x
  ``bitpix``) is cut off silently.

:func:`check_volume_file` reads the header itself (a few KB; compressed data is
streamed and counted, never held) and refuses each of these with the file, the
header field and the value; :func:`check_geometry` checks what a reader
returned (spacing, origin, direction) for every other format ITK reads.
"""

from __future__ import annotations

import bz2
import gzip
import math
import struct
import zlib
from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError

#: largest header read [bytes]: a real NRRD header is < 4 KB; more is not a header
MAX_HEADER_BYTES = 1 << 20
#: ``max |D^T D - I|`` allowed for an orthonormal direction matrix: the tolerance of
#: ``FluoTomoLib.meshing.voxel.check_direction``, the mesher's own check (a float32
#: NIfTI matrix is orthonormal to ~1e-7)
ORTHONORMAL_TOL = 1e-5

_NRRD_TYPES = {}
for _names, _size in ((("signed char", "int8", "int8_t"), 1),
                      (("uchar", "unsigned char", "uint8", "uint8_t"), 1),
                      (("short", "short int", "signed short", "signed short int", "int16",
                        "int16_t"), 2),
                      (("ushort", "unsigned short", "unsigned short int", "uint16", "uint16_t"), 2),
                      (("int", "signed int", "int32", "int32_t"), 4),
                      (("uint", "unsigned int", "uint32", "uint32_t"), 4),
                      (("longlong", "long long", "long long int", "signed long long",
                        "signed long long int", "int64", "int64_t"), 8),
                      (("ulonglong", "unsigned long long", "unsigned long long int", "uint64",
                        "uint64_t"), 8),
                      (("float",), 4), (("double",), 8)):
    for _n in _names:
        _NRRD_TYPES[_n] = _size
# axis kinds that are positions in space (others: list, vector, RGB-color, ...)
_SPATIAL_KINDS = {"domain", "space", "???", "none", ""}


def check_volume_file(path, field=None, copies=None):
    """Refuse a NRRD or NIfTI file whose header lies; other suffixes pass.

    Parameters
    ----------
    path : str or Path
        ``.nrrd`` / ``.nhdr`` (``.seg.nrrd``, ``.seq.nrrd``) or ``.nii`` /
        ``.nii.gz`` / ``.hdr``.
    field : str, optional
        The option or node the file came from, put before the header field.
    copies : float, optional
        How many copies of the voxel data the caller holds at its peak: the
        declared size times this is checked against the memory left
        (``fluoguide.memory``) before anything is decompressed.

    Returns
    -------
    dict or None
        ``shape`` (sizes, fastest axis first) and ``bytes`` (declared data size)
        of a NRRD or NIfTI file; None for another format.

    Raises
    ------
    FluoInputError
        Naming the file, ``field: header field`` and the value.
    """
    p = Path(path)
    name = p.name.lower()
    if name.endswith((".nrrd", ".nhdr")):
        return _check_nrrd(p, field, copies)
    if name.endswith((".nii", ".nii.gz", ".hdr")):
        return _check_nifti(p, field, copies)
    return None


def check_geometry(spacing, origin, direction, file=None, field=None):
    """Refuse a volume geometry that is not finite, positive and orthonormal.

    Parameters
    ----------
    spacing : (3,) array_like
        Voxel size [mm].
    origin : (3,) array_like
        Position of voxel (0, 0, 0) [mm].
    direction : (3, 3) array_like
        Direction cosines (columns: the index axes).
    file, field : optional
        For the message (``field`` is put before ``spacing``, ``origin``, ...).
    """
    def where(name):
        return f"{field}: {name}" if field else name

    spacing = np.asarray(spacing, float).ravel()
    origin = np.asarray(origin, float).ravel()
    d = np.asarray(direction, float)
    if not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
        raise FluoInputError("voxel spacing must be positive and finite [mm]", file=file,
                             field=where("spacing"), value=spacing.tolist())
    if not np.all(np.isfinite(origin)):
        raise FluoInputError("origin must be finite [mm]", file=file, field=where("origin"),
                             value=origin.tolist())
    if d.size != len(spacing) ** 2 or not np.all(np.isfinite(d)):
        raise FluoInputError("direction must be a finite square matrix", file=file,
                             field=where("direction"), value=d.ravel().tolist())
    d = d.reshape(len(spacing), len(spacing))
    if np.max(np.abs(d.T @ d - np.eye(len(d)))) > ORTHONORMAL_TOL:
        raise FluoInputError("direction is not orthonormal (skewed or scaled axes)", file=file,
                             field=where("direction"), value=np.round(d, 6).tolist())


def _check_memory(declared, copies, shape, p, field):
    if copies is None:
        return
    from fluoguide.memory import check_fits

    check_fits(declared * copies, f"reading the volume ({' x '.join(map(str, shape))} voxels)",
               "crop or resample it first", file=p, field=field)


# ----------------------------------------------------------------- NRRD
def _nrrd_header(p, field):
    """(header fields dict, byte offset of the data or None when detached)."""
    try:
        with open(p, "rb") as fh:
            head = fh.read(MAX_HEADER_BYTES)
    except OSError as exc:
        raise FluoInputError(f"cannot read ({exc.strerror})", file=p, field=field) from None
    if not head.startswith(b"NRRD000"):
        raise FluoInputError("not a NRRD file (no NRRD000x magic)", file=p, field=field)
    end = head.find(b"\n\n")
    crlf = head.find(b"\r\n\r\n")
    if crlf >= 0 and (end < 0 or crlf < end):
        offset = crlf + 4
    elif end >= 0:
        offset = end + 2
    else:
        offset = None                       # a detached header (.nhdr) or a cut one
    text = head[: (offset if offset is not None else len(head))]
    fields = {}
    for raw in text.decode("latin-1").splitlines()[1:]:
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        key, sep, value = line.partition(": ")
        if not sep or ":=" in key:
            continue                        # "key:=value" pairs are metadata, not layout
        key = key.strip().lower()
        if key in fields:                   # which one a reader takes is its own choice
            raise FluoInputError("header field given twice", file=p,
                                 field=f"{field}: {key}" if field else key, value=value.strip())
        fields[key] = value.strip()
    return fields, offset


def _nrrd_vector(text):
    """(x, y, z) of a NRRD vector ``(1,0,0)``; None for ``none``."""
    t = text.strip()
    if t.lower() == "none":
        return None
    if not (t.startswith("(") and t.endswith(")")):
        raise ValueError(t)
    return [float(v) for v in t[1:-1].split(",")]


def _split_vectors(text):
    """The items of ``space directions``: ``(..) (..) none``."""
    out, depth, cur = [], 0, ""
    for ch in text:
        if ch == "(":
            depth += 1
        elif ch == ")":
            depth -= 1
        if ch.isspace() and depth == 0:
            if cur:
                out.append(cur)
            cur = ""
        else:
            cur += ch
    if cur:
        out.append(cur)
    return out


def _check_nrrd(p, field, copies):
    fields, offset = _nrrd_header(p, field)

    def bad(problem, key, value=None):
        return FluoInputError(problem, file=p, field=f"{field}: {key}" if field else key,
                              value=value)

    try:
        dim = int(fields["dimension"])
        sizes = [int(v) for v in fields["sizes"].split()]
    except KeyError as exc:
        raise bad("required header field missing", exc.args[0]) from None
    except ValueError:
        raise bad("must be integers", "sizes", fields.get("sizes")) from None
    if not 1 <= dim <= 16 or len(sizes) != dim or min(sizes) < 1:
        raise bad(f"must be {dim} positive integers (dimension {dim})", "sizes",
                  fields.get("sizes"))
    kinds = fields.get("kinds", "").split()
    spatial = [i >= len(kinds) or kinds[i].lower() in _SPATIAL_KINDS for i in range(dim)]
    if "spacings" in fields:
        vals = fields["spacings"].split()
        if len(vals) != dim:
            raise bad(f"must be {dim} numbers", "spacings", fields["spacings"])
        for i, v in enumerate(vals):
            try:
                s = float(v)
            except ValueError:
                raise bad("must be numbers", "spacings", fields["spacings"]) from None
            # ITK reads a NaN spacing as 1 and a negative one as a flipped axis
            if spatial[i] and not (math.isfinite(s) and s > 0):
                raise bad(f"voxel spacing of axis {i} must be positive and finite [mm]",
                          "spacings", fields["spacings"])
    columns = []
    if "space directions" in fields:
        items = _split_vectors(fields["space directions"])
        if len(items) != dim:
            raise bad(f"must be {dim} vectors or 'none'", "space directions",
                      fields["space directions"])
        for i, item in enumerate(items):
            try:
                v = _nrrd_vector(item)
            except ValueError:
                raise bad("must be vectors like (1,0,0) or 'none'", "space directions",
                          fields["space directions"]) from None
            if v is None:
                continue
            v = np.array(v)
            norm = float(np.linalg.norm(v)) if np.all(np.isfinite(v)) else float("nan")
            if not (math.isfinite(norm) and norm > 0):
                raise bad(f"axis {i}: must be finite and not zero (its length is the voxel "
                          "size)", "space directions", fields["space directions"])
            columns.append(v / norm)
    if len(columns) > 1:
        d = np.array(columns).T
        if np.max(np.abs(d.T @ d - np.eye(d.shape[1]))) > ORTHONORMAL_TOL:
            # ITK normalises each axis and keeps the skew: a direction no mesher can use
            raise bad("axes are not orthogonal (a skewed grid)", "space directions",
                      fields["space directions"])
    if "space origin" in fields:
        try:
            o = _nrrd_vector(fields["space origin"])
        except ValueError:
            raise bad("must be a vector like (0,0,0)", "space origin",
                      fields["space origin"]) from None
        if o is None or not all(math.isfinite(x) for x in o):
            raise bad("must be finite [mm]", "space origin", fields["space origin"])
    kind = fields.get("type", "").lower()
    size = _NRRD_TYPES.get(kind)
    if size is None:
        if kind != "block":
            raise bad("unknown voxel type", "type", fields.get("type"))
        try:
            size = int(fields.get("block size", fields.get("blocksize", "")))
        except ValueError:
            raise bad("a block type needs a block size", "block size",
                      fields.get("block size")) from None
    declared = int(np.prod(sizes, dtype=object)) * size
    out = {"shape": sizes, "bytes": declared}
    _check_memory(declared, copies, sizes, p, field)
    encoding = fields.get("encoding", "").lower()
    skipped = fields.get("line skip", "0") not in ("0", "") or \
        fields.get("byte skip", "0") not in ("0", "")
    text = encoding in ("ascii", "text", "txt")
    if skipped or not (text or encoding in ("raw", "gzip", "gz", "bzip2", "bz2")):
        return out              # hex and skips: the reader counts itself
    if "data file" in fields or "datafile" in fields:
        name = fields.get("data file", fields.get("datafile")).strip()
        if " " in name or name.upper().startswith("LIST"):
            return out          # a list or a pattern of files: not checked here
        data_path, start = (p.parent / name), 0
        if not data_path.is_file():
            raise bad("data file not found", "data file", name)
    elif offset is None:
        raise bad("header does not end (no blank line before the data)", "header")
    else:
        data_path, start = p, offset
    if text:
        _check_text_values(data_path, start, p, field)     # the reader counts the values
        return out
    _check_data_length(data_path, start, declared, encoding, p, field, "sizes x type")
    return out


#: the longest value text data may hold: a double with every digit is 24 characters
MAX_TEXT_VALUE = 64


def _check_text_values(data_path, start, header_path, field):
    """Refuse a value longer than :data:`MAX_TEXT_VALUE` characters in a NRRD's
    text (ascii) data: teem copies the value into a fixed buffer to report it,
    and 1,500 characters crash ITK's reader (SIGSEGV: no message, and the web
    app's server gone). Read 1 MiB at a time."""
    import re

    long_run = re.compile(rb"[^\s]{%d,}" % (MAX_TEXT_VALUE + 1))
    key = f"{field}: data" if field else "data"
    with open(data_path, "rb") as fh:
        fh.seek(start)
        tail = b""
        while True:
            chunk = fh.read(1 << 20)
            if not chunk:
                break
            buf = tail + chunk
            m = long_run.search(buf)
            if m:
                raise FluoInputError(f"text data hold a value of more than {MAX_TEXT_VALUE} "
                                     "characters (not a number)", file=header_path, field=key,
                                     value=m.group(0)[:20].decode("latin-1") + "...")
            tail = buf[-MAX_TEXT_VALUE:]


# ----------------------------------------------------------------- NIfTI
#: header fields: (NIfTI-1 struct format, byte offset, NIfTI-2 format, offset)
_NIFTI_FIELDS = {"dim": ("8h", 40, "8q", 16), "datatype": ("h", 70, "h", 12),
                 "bitpix": ("h", 72, "h", 14), "pixdim": ("8f", 76, "8d", 104),
                 "vox_offset": ("f", 108, "q", 168), "qform_code": ("h", 252, "i", 344),
                 "sform_code": ("h", 254, "i", 348), "quatern": ("3f", 256, "3d", 352),
                 "qoffset": ("3f", 268, "3d", 376), "srow": ("12f", 280, "12d", 400)}
_NIFTI_BYTES = {2: 1, 4: 2, 8: 4, 16: 4, 32: 8, 64: 8, 128: 3, 256: 1, 512: 2, 768: 4,
                1024: 8, 1280: 8, 1536: 16, 1792: 16, 2048: 32, 2304: 4}


def _open_maybe_gz(p):
    with open(p, "rb") as fh:
        magic = fh.read(2)
    return gzip.open(p, "rb") if magic == b"\x1f\x8b" else open(p, "rb")


def _check_nifti(p, field, copies):
    def bad(problem, key, value=None):
        return FluoInputError(problem, file=p, field=f"{field}: {key}" if field else key,
                              value=value)

    try:
        with _open_maybe_gz(p) as fh:
            head = fh.read(544)
    except (OSError, EOFError, zlib.error) as exc:
        raise FluoInputError(f"cannot read the NIfTI header ({exc})", file=p,
                             field=field) from None
    if len(head) < 348:
        raise bad("NIfTI header cut short", "sizeof_hdr", len(head))
    for end in "<>":
        n = struct.unpack_from(end + "i", head, 0)[0]
        if n in (348, 540):
            break
    else:
        raise bad("not a NIfTI header (sizeof_hdr is not 348 or 540)", "sizeof_hdr",
                  struct.unpack_from("<i", head, 0)[0])
    if n == 540 and len(head) < 540:
        raise bad("NIfTI-2 header cut short", "sizeof_hdr", len(head))
    version = 0 if n == 348 else 1
    f = {name: struct.unpack_from(end + layout[2 * version], head, layout[2 * version + 1])
         for name, layout in _NIFTI_FIELDS.items()}
    dim, pixdim, quatern, qoffset = f["dim"], f["pixdim"], f["quatern"], f["qoffset"]
    (datatype,), (bitpix,), (vox_offset,) = f["datatype"], f["bitpix"], f["vox_offset"]
    (qform_code,), (sform_code,) = f["qform_code"], f["sform_code"]
    srow = np.array(f["srow"], float).reshape(3, 4)
    magic = head[344:347] if version == 0 else head[4:7]
    single = magic in (b"n+1", b"n+2")
    # an Analyze 7.5 header (no NIfTI magic) has other fields where the transforms are
    nifti = single or magic in (b"ni1", b"ni2")
    if not nifti:
        qform_code = sform_code = 0
    ndim = dim[0]
    if not 1 <= ndim <= 7 or min(dim[1:ndim + 1]) < 1:
        raise bad("must give 1 to 7 axes of at least one voxel", "dim", list(dim))
    nspace = min(ndim, 3)
    for i in range(1, nspace + 1):
        # ITK turns NaN and 0 into 1 and a negative size into a flipped axis
        if not (math.isfinite(pixdim[i]) and pixdim[i] > 0):
            raise bad("voxel size must be positive and finite [mm]", f"pixdim[{i}]",
                      float(pixdim[i]))
    if qform_code > 0:
        for name, vals in (("quatern_b/c/d", quatern), ("qoffset_x/y/z", qoffset)):
            if not all(math.isfinite(v) for v in vals):
                raise bad("must be finite", name, [float(v) for v in vals])
        if sum(v * v for v in quatern) > 1.0 + 1e-5:
            raise bad("not a rotation quaternion (b^2 + c^2 + d^2 > 1)", "quatern_b/c/d",
                      [float(v) for v in quatern])
    if sform_code > 0:
        if not np.all(np.isfinite(srow)):
            raise bad("must be finite", "srow_x/y/z", srow.tolist())
        m = srow[:, :3]
        scales = np.linalg.norm(m, axis=0)
        if np.any(scales <= 0):
            raise bad("an axis has length 0", "srow_x/y/z", srow.tolist())
        d = m / scales
        if np.max(np.abs(d.T @ d - np.eye(3))) > ORTHONORMAL_TOL:
            # ITK says "unexpected scales in sform" and silently takes the qform
            raise bad("axes are not orthogonal (a skewed grid)", "srow_x/y/z", srow.tolist())
        pd = np.array(pixdim[1:4], float)[:nspace]
        if np.any(np.abs(scales[:nspace] - pd) > 1e-4 * np.maximum(scales[:nspace], pd)):
            # two voxel sizes in one file: ITK picks one and says so only on stderr
            raise bad(f"the sform's voxel size {np.round(scales[:nspace], 6).tolist()} mm "
                      "differs from pixdim's", "pixdim", [float(v) for v in pd])
    nbytes = _NIFTI_BYTES.get(datatype)
    if nbytes is None or bitpix != 8 * nbytes:
        raise bad("unknown datatype, or bitpix does not match it", "datatype",
                  (int(datatype), int(bitpix)))
    shape = [int(v) for v in dim[1:ndim + 1]]
    declared = int(np.prod(shape, dtype=object)) * nbytes
    out = {"shape": shape, "bytes": declared}
    _check_memory(declared, copies, shape, p, field)
    if not (math.isfinite(vox_offset) and vox_offset >= (n + 4 if single else 0)):
        raise bad("data offset must be past the header", "vox_offset", float(vox_offset))
    if single:
        data_path, start = p, int(vox_offset)
    else:                   # a .hdr/.img pair
        data_path = p.with_name(p.name[:-4] + ".img") if p.name.lower().endswith(".hdr") \
            else None
        if data_path is None or not data_path.is_file():
            return out      # the reader finds (or misses) the data file itself
        start = int(vox_offset)
    with open(data_path, "rb") as fh:
        compressed = fh.read(2) == b"\x1f\x8b"
    _check_data_length(data_path, start, declared, "gzip" if compressed else "raw", p, field,
                       "dim x bitpix", offset_in_stream=compressed)
    return out


# ----------------------------------------------------------------- data length
def _decompressor(encoding):
    if encoding in ("bzip2", "bz2"):
        return bz2.BZ2Decompressor()
    return zlib.decompressobj(zlib.MAX_WBITS | 32)          # gzip or zlib header


def _decompressed_length(path, start, encoding, limit):
    """Bytes of the compressed stream(s) from byte ``start`` of ``path``, counted
    up to ``limit`` (1 MiB read at a time; concatenated members continue it,
    as gzread reads them)."""
    dec = _decompressor(encoding)
    have = 0
    with open(path, "rb") as fh:
        fh.seek(start)
        pending = b""
        while have < limit:
            chunk = pending or fh.read(1 << 20)
            pending = b""
            if not chunk:
                break
            have += len(dec.decompress(chunk, limit - have))
            tail = getattr(dec, "unconsumed_tail", b"")     # zlib: output limit reached
            if tail:
                pending = tail
                continue
            if dec.eof:
                rest = dec.unused_data + fh.read(4)
                if not rest.startswith((b"\x1f\x8b", b"BZh")):
                    break                           # the stream ended
                dec = _decompressor("bz2" if rest.startswith(b"BZh") else "gzip")
                pending = rest
    return have


def _check_data_length(data_path, start, declared, encoding, header_path, field, what,
                       offset_in_stream=False):
    """Refuse data longer or shorter than the header declares.

    ``start`` is the data's byte offset in the file (raw), or in the
    decompressed stream when ``offset_in_stream`` (a .nii.gz is compressed whole).
    Compressed data are streamed and counted in 1 MiB pieces, stopping as soon
    as the count passes what was declared.
    """
    key = f"{field}: data" if field else "data"
    if encoding == "raw":
        have = data_path.stat().st_size - start
    else:
        # stop one byte past what was declared: enough to know it is more
        limit = declared + (start if offset_in_stream else 0) + 1
        try:
            have = _decompressed_length(data_path, 0 if offset_in_stream else start,
                                        encoding, limit)
        except (OSError, EOFError, ValueError, zlib.error) as exc:
            raise FluoInputError(f"compressed data are damaged ({exc})", file=header_path,
                                 field=key) from None
        if offset_in_stream:
            have -= start
    if have > declared:
        raise FluoInputError(f"more data than the header declares ({what} = {declared} bytes): "
                             "a reader would cut the rest off silently", file=header_path,
                             field=key, value=f">= {have} bytes" if encoding != "raw"
                             else f"{have} bytes")
    if have < declared:
        raise FluoInputError(f"cut short: the header declares {what} = {declared} bytes",
                             file=header_path, field=key, value=f"{max(have, 0)} bytes")
