"""Bounds on the work a recording's bytes can ask for, checked before the work is done.

A schema is checked before a protobuf descriptor pool or a ROS 2 parser is built from it (both
recurse once per nesting level and per type in a chain, and so fail with ``RecursionError`` or take
minutes on a hostile schema); an image's width and height are read from its header before OpenCV
allocates its pixels. Each bound is a named constant, far above any real recording and far below
what would hurt; breaking one raises :class:`CodecError` in one line saying which and by how much.
"""

from __future__ import annotations

import re
import struct

from google.protobuf import descriptor_pb2

from slamreplay.recorder.errors import CodecError

# Nesting of a schema: nested message declarations, a chain of message-typed fields, or a chain of file
# dependencies. Foxglove's schemas nest 3 deep, ROS 2's common messages 4; Python's recursion (1000) is
# reached by a chain of a few hundred in the libraries that build decoders.
MAX_SCHEMA_DEPTH = 64
# Message types in one schema: Foxglove's have under 10, a rosbag2 concatenated definition a few dozen;
# each costs a class built at read time.
MAX_SCHEMA_TYPES = 10_000
# Pixels of one image: 32 Mpx is above any robot camera (a 4K frame is 8.3 Mpx) and keeps one decoded
# rgb8 frame under 100 MB; a header claiming 40,000 x 40,000 (1.6 Gpx, 4.8 GB) is refused undecoded.
MAX_IMAGE_PIXELS = 32 << 20
# Pixels along one side: JPEG's own maximum (65,535), and far below OpenCV's (2**20), which raises an assertion
# error of its own beyond it (a 4,128,776 x 6 BMP header is under MAX_IMAGE_PIXELS).
MAX_IMAGE_SIDE = (1 << 16) - 1

# Chunks of one PNG, each checked (CRC) in Python before OpenCV sees the bytes: libpng writes 8 KiB IDAT
# chunks, so the largest image slamreplay decodes (MAX_IMAGE_PIXELS rgb8) needs ~12,300; a PNG of a million
# empty chunks (12 MB that compress to almost nothing) would cost seconds per message.
MAX_PNG_CHUNKS = 1 << 16
# Nesting of JSON held in a recording's metadata (the sensor model, the source): Python's json parser recurses
# once per level and raises RecursionError near 1000; slamreplay's own JSON nests 3 deep.
MAX_JSON_DEPTH = 64

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}  # start-of-frame markers (not DHT, JPG, DAC)
_ROS_PRIMITIVES = frozenset(("bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
                             "uint32", "int64", "uint64", "string", "wstring", "time", "duration"))


def shown(text: str, limit: int = 100) -> str:
    """A string from a file (topic, schema name...) as it may appear in a one-line message: printable, bounded."""
    text = "".join(c if c.isprintable() else "?" for c in text)
    return text if len(text) <= limit else text[:limit] + "..."


def json_depth(text: str) -> int:
    """How deep the arrays and objects of a JSON text nest (strings skipped), without parsing it."""
    depth = deepest = 0
    in_string = escaped = False
    for c in text:  # one pass, no regular expression: an unterminated string must not cost quadratic time
        if in_string:
            if escaped:
                escaped = False
            elif c == "\\":
                escaped = True
            elif c == '"':
                in_string = False
        elif c == '"':
            in_string = True
        elif c in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif c in "]}":
            depth -= 1
    return deepest


def _longest_chain(edges: dict[str, list[str]], roots: list[str]) -> tuple[int, bool]:
    """Length of the longest path of ``edges`` from ``roots`` (a back edge ends a path), and whether
    there is a cycle; iterative, so that a chain of any length costs no recursion."""
    depth: dict[str, int] = {}
    on_stack: set[str] = set()
    best, cyclic = 0, False
    for root in roots:
        if root in depth:
            best = max(best, depth[root])
            continue
        stack: list[tuple[str, int]] = [(root, 0)]
        on_stack.add(root)
        while stack:
            node, i = stack[-1]
            children = edges.get(node, [])
            if i < len(children):
                stack[-1] = (node, i + 1)
                child = children[i]
                cyclic = cyclic or child in on_stack
                if child not in depth and child not in on_stack and child in edges:
                    stack.append((child, 0))
                    on_stack.add(child)
                continue
            depth[node] = 1 + max((depth.get(c, 0) for c in children if c not in on_stack), default=0)
            on_stack.discard(node)
            stack.pop()
        best = max(best, depth[root])
    return best, cyclic


def _too_deep(kind: str, depth: int) -> CodecError:
    return CodecError(f"the schema nests {kind} {depth} deep, beyond slamreplay's limit of {MAX_SCHEMA_DEPTH}: "
                      f"it is damaged or hostile")


def check_protobuf_schema(data: bytes) -> None:
    """CodecError when a FileDescriptorSet nests or holds more than the bounds allow.

    Raises protobuf's DecodeError when ``data`` is not a FileDescriptorSet: upb parses it with its own
    depth limit (100), so a set nested deeper is refused there, without recursion in Python.
    """
    fds = descriptor_pb2.FileDescriptorSet.FromString(data)
    edges: dict[str, list[str]] = {}
    nesting = 0
    pending = [(f".{fd.package}" if fd.package else "", m, 1) for fd in fds.file for m in fd.message_type]
    while pending:
        scope, m, level = pending.pop()
        nesting = max(nesting, level)
        if nesting > MAX_SCHEMA_DEPTH:
            raise _too_deep("message declarations", nesting)
        if len(edges) >= MAX_SCHEMA_TYPES:
            raise CodecError(f"the schema declares more than {MAX_SCHEMA_TYPES:,} message types, beyond "
                             f"slamreplay's limit: it is damaged or hostile")
        name = f"{scope}.{m.name}"
        edges[name] = [f.type_name for f in m.field if f.type_name]
        pending.extend((name, n, level + 1) for n in m.nested_type)
    for name, targets in edges.items():
        edges[name] = [_resolve(name, t, edges) for t in targets]
    chain, _ = _longest_chain(edges, list(edges))  # recursive types are legal: upb bounds their decoding
    if chain > MAX_SCHEMA_DEPTH:
        raise _too_deep("message-typed fields", chain)
    files = {fd.name: list(fd.dependency) for fd in fds.file}
    chain, _ = _longest_chain(files, list(files))
    if chain > MAX_SCHEMA_DEPTH:
        raise _too_deep("file dependencies", chain)


def _resolve(scope: str, type_name: str, known: dict[str, list[str]]) -> str:
    """A field's type as a full name: absolute (``.pkg.T``), or relative, looked up from the field's
    message outwards as protoc does."""
    if type_name.startswith("."):
        return type_name
    parts = scope.split(".")
    for i in range(len(parts), 0, -1):
        candidate = ".".join(parts[:i]) + "." + type_name
        if candidate in known:
            return candidate
    return "." + type_name


def check_ros2_schema(text: str, name: str) -> None:
    """CodecError when a ros2msg definition (with its ``MSG:`` sections) nests, recurses or holds too much."""
    # split and named as mcap_ros2 does: a section is named by a leading "MSG:" line, else by the one before
    sections = re.split(r"^={3,}$", text, flags=re.MULTILINE)
    if len(sections) > MAX_SCHEMA_TYPES:
        raise CodecError(f"the schema holds {len(sections):,} message definitions, beyond slamreplay's limit of "
                         f"{MAX_SCHEMA_TYPES:,}: it is damaged or hostile")
    edges: dict[str, list[str]] = {}
    current = name
    for section in sections:
        section = section.strip()
        found = re.match(r"^MSG:\s+(\S+)$", section, flags=re.MULTILINE)
        current = found.group(1) if found else current
        own = _ros_name(current, "")
        pkg = own.split("/")[0]
        fields = edges.setdefault(own, [])
        for line in section.splitlines():
            line = line.split("#", 1)[0].strip()
            if not line or line.startswith("MSG:") or "=" in line:
                continue
            ftype = line.split()[0].split("[", 1)[0].split("<=", 1)[0]  # pkg/T[<=3], string<=5: no regex backtracking
            if ftype in _ROS_PRIMITIVES:
                continue
            tokens = line.split()
            # a default value on a message-typed field: rosidl's parser raises NotImplementedError on it (a bad
            # field name is found first by the parser, as InvalidFieldDefinition or NameError)
            if len(tokens) > 2 and re.fullmatch(r"[a-z][a-z0-9_]*", tokens[1]):
                raise CodecError(f"the schema gives the field {tokens[1]} of message type "
                                 f"{shown(ftype, 60)} a default value, which ROS 2 allows only for primitive types")
            fields.append(_ros_name(ftype, pkg))
    chain, cyclic = _longest_chain(edges, list(edges))
    if chain > MAX_SCHEMA_DEPTH:
        raise _too_deep("message-typed fields", chain)
    if cyclic:  # ROS 2 forbids recursive messages, and the CDR decoder would recurse as deep as the bytes go
        raise CodecError("the schema holds a message type that contains itself, which ROS 2 does not allow: "
                         "it is damaged or hostile")


def _ros_name(ftype: str, pkg: str) -> str:
    """``pkg/msg/Type``, ``pkg/Type`` or ``Type`` (in ``pkg``; ``Header`` is std_msgs') as ``pkg/Type``."""
    parts = ftype.split("/")
    if len(parts) == 1:
        return "std_msgs/Header" if ftype == "Header" else f"{pkg}/{ftype}"
    return f"{parts[0]}/{parts[-1]}"


# Formats OpenCV recognises by their first bytes (it ignores file names): those whose size slamreplay reads from the
# header are decoded; the others are refused undecoded, since their headers could claim any size unchecked.
_UNSIZED_FORMATS = ((b"GIF87a", "GIF"), (b"GIF89a", "GIF"), (b"#?RADIANCE", "Radiance HDR"),
                    (b"#?RGBE", "Radiance HDR"), (b"\x59\xa6\x6a\x95", "Sun raster"), (b"Pf", "PFM"),
                    (b"PF", "PFM"), (b"P7", "PAM"),
                    (b"\x00\x00\x00\x0cjP  ", "JPEG 2000"), (b"\xff\x4f\xff\x51", "JPEG 2000"),
                    (b"\x76\x2f\x31\x01", "OpenEXR"))
SIZED_FORMATS = frozenset(("PNG", "JPEG", "TIFF", "BMP", "PNM"))  # PNM: PBM, PGM, PPM
_TIFF_MAX_TAGS = 4096  # entries of a TIFF's first directory read to find its size (a real one has 10-30)


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    pos = 2
    while pos + 4 <= len(data):  # markers: 0xFF, kind, then a big-endian segment length (itself included)
        if data[pos] != 0xFF:
            return None
        kind = data[pos + 1]
        if kind == 0xFF:  # fill byte
            pos += 1
            continue
        (length,) = struct.unpack_from(">H", data, pos + 2)
        if kind in _JPEG_SOF:
            if pos + 9 > len(data):
                return None
            h, w = struct.unpack_from(">HH", data, pos + 5)
            return int(w), int(h)
        if kind == 0xDA or length < 2:  # scan data: no frame header came first
            return None
        pos += 2 + length
    return None


def _bmp_size(data: bytes) -> tuple[int, int] | None:
    if len(data) < 26:
        return None
    (header,) = struct.unpack_from("<I", data, 14)
    if header == 12:  # OS/2 BITMAPCOREHEADER: 16-bit sizes
        w, h = struct.unpack_from("<HH", data, 18)
        return int(w), int(h)
    w, h = struct.unpack_from("<ii", data, 18)
    return abs(int(w)), abs(int(h))  # a negative height: rows stored top-down


def _pnm_size(data: bytes) -> tuple[int, int] | None:
    numbers: list[int] = []
    for line in data[2:4096].split(b"\n"):
        for token in line.split(b"#", 1)[0].split():
            if not token.isdigit():
                return None
            numbers.append(int(token))
            if len(numbers) == 2:
                return numbers[0], numbers[1]
    return None


def _tiff_size(data: bytes) -> tuple[int, int] | None:
    if len(data) < 8:
        return None
    order = "<" if data[:2] == b"II" else ">"
    (version,) = struct.unpack_from(order + "H", data, 2)
    big = version == 43
    if big:  # BigTIFF: 8-byte offsets and counts, 20-byte entries
        if len(data) < 16:
            return None
        (ifd,) = struct.unpack_from(order + "Q", data, 8)
        count_fmt, entry, value_at = "Q", 20, 12
    else:
        (ifd,) = struct.unpack_from(order + "I", data, 4)
        count_fmt, entry, value_at = "H", 12, 8
    count_size = struct.calcsize(count_fmt)
    if ifd + count_size > len(data):
        return None
    (count,) = struct.unpack_from(order + count_fmt, data, ifd)
    size: dict[int, int] = {}
    for k in range(min(count, _TIFF_MAX_TAGS)):
        at = ifd + count_size + k * entry
        if at + entry > len(data):
            return None
        tag, kind = struct.unpack_from(order + "HH", data, at)
        fmt = {3: "H", 4: "I", 16: "Q"}.get(kind, "")  # ImageWidth, ImageLength as SHORT, LONG or LONG8 (BigTIFF)
        if tag in (256, 257) and fmt and struct.calcsize(fmt) <= entry - value_at:
            (size[tag],) = struct.unpack_from(order + fmt, data, at + value_at)
            if len(size) == 2:
                return size[256], size[257]
    return None


def image_format(data: bytes) -> str | None:
    """The format OpenCV would decode ``data`` as, from its first bytes ("PNG", "GIF"...); None when none."""
    if data.startswith(_PNG_SIGNATURE):
        return "PNG"
    if data.startswith(b"\xff\xd8\xff"):
        return "JPEG"
    if data[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return "TIFF"
    if data.startswith(b"BM"):
        return "BMP"
    if len(data) > 2 and data[:1] == b"P" and data[1:2] in b"123456" and data[2:3].isspace():
        return "PNM"
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "WebP"
    if data[4:8] == b"ftyp":
        return "HEIF/AVIF"
    return next((name for magic, name in _UNSIZED_FORMATS if data.startswith(magic)), None)


def image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from the header of a PNG, JPEG, TIFF, BMP or PNM image; None when there is none to read."""
    fmt = image_format(data)
    if fmt == "PNG":
        if len(data) >= 24 and data[12:16] == b"IHDR":
            w, h = struct.unpack_from(">II", data, 16)
            return int(w), int(h)
        return None
    reader = {"JPEG": _jpeg_size, "TIFF": _tiff_size, "BMP": _bmp_size, "PNM": _pnm_size}.get(fmt or "")
    return reader(data) if reader is not None else None


def check_image_size(data: bytes, fmt: str) -> None:
    """CodecError when an image's header claims more than MAX_IMAGE_PIXELS pixels (or none, or a side longer than
    MAX_IMAGE_SIDE), when it is a format whose size slamreplay does not read, or when its header is too damaged
    to tell; no decoding.

    ``data`` must hold the image's header (for a TIFF, its first directory: the whole file is safest).
    """
    kind = image_format(data)
    if kind is None:
        return  # not an image format OpenCV knows: it refuses the bytes without allocating pixels
    if kind not in SIZED_FORMATS:
        raise CodecError(f"the {fmt or 'image'} data is a {kind} image, which slamreplay does not decode (only "
                         f"{', '.join(sorted(SIZED_FORMATS))})")
    size = image_size(data)
    if size is None:
        raise CodecError(f"the {fmt or 'image'} data is a {kind} image whose header does not say its size: the image "
                         f"is damaged")
    w, h = size
    if w == 0 or h == 0 or w * h > MAX_IMAGE_PIXELS:
        raise CodecError(f"the {fmt or 'image'} header claims {w:,} x {h:,} pixels; slamreplay decodes at most "
                         f"{MAX_IMAGE_PIXELS:,} pixels per image: the image is damaged or hostile")
    if max(w, h) > MAX_IMAGE_SIDE:
        raise CodecError(f"the {fmt or 'image'} header claims {w:,} x {h:,} pixels; slamreplay decodes at most "
                         f"{MAX_IMAGE_SIDE:,} pixels along a side: the image is damaged or hostile")
