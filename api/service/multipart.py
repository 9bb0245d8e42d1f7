"""Form uploads (``curl -F file=@run.mcap``): the ``file`` part of a multipart/form-data body, as a stream.

The body is parsed as it arrives (python-multipart's push parser), so the file is never whole
in memory and the upload size limit holds as for a raw body. Parts before the file part are
read (their bytes count against the limit) and dropped, but for the first KiB of each text field,
which the caller may ask for (the page's form sends its CSRF token first); the body after the file
part is not read. A form without a ``file`` part is refused with the name of the field to use.
"""

from __future__ import annotations

from collections.abc import AsyncIterator

from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MAX_BOUNDARY_LENGTH, MultipartParser, parse_options_header

from slamreplay.api.service.errors import ApiError, TooLargeError

FILE_FIELD = "file"
FIELD_BYTES = 1024
USAGE = f"curl -F {FILE_FIELD}=@run.mcap URL/recordings (or the raw file: curl --data-binary @run.mcap URL/recordings)"


class FormError(ApiError):
    """A form upload without the file where it belongs, or a malformed multipart body."""

    status = 422


def is_form(content_type: str | None) -> bool:
    """Whether a request's Content-Type is multipart/form-data."""
    return (content_type or "").split(";")[0].strip().lower() == "multipart/form-data"


class _Parts:
    """Callbacks of the push parser: finds the ``file`` part and collects its data."""

    def __init__(self) -> None:
        self.header_field = b""
        self.header_value = b""
        self.disposition = b""
        self.in_file = False
        self.file_started = False
        self.file_ended = False
        self.filename: str | None = None
        self.other_fields: list[str] = []
        self.other_files: list[str] = []
        self.pending: list[bytes] = []
        self.fields: dict[str, bytes] = {}  # text fields before the file part: their first FIELD_BYTES bytes
        self.field: str | None = None

    def callbacks(self) -> dict[str, object]:
        return {"on_part_begin": self.on_part_begin, "on_header_field": self.on_header_field,
                "on_header_value": self.on_header_value, "on_header_end": self.on_header_end,
                "on_headers_finished": self.on_headers_finished, "on_part_data": self.on_part_data,
                "on_part_end": self.on_part_end}

    def on_part_begin(self) -> None:
        self.disposition = b""

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self.header_field += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self.header_value += data[start:end]

    def on_header_end(self) -> None:
        if self.header_field.strip().lower() == b"content-disposition":
            self.disposition = self.header_value
        self.header_field, self.header_value = b"", b""

    def on_headers_finished(self) -> None:
        _, params = parse_options_header(self.disposition)
        name = params.get(b"name", b"").decode("utf-8", "replace")
        filename = params.get(b"filename")
        if name == FILE_FIELD and not self.file_started:
            self.in_file = self.file_started = True
            self.filename = filename.decode("utf-8", "replace") if filename is not None else None
        elif filename is not None:
            self.other_files.append(name)
        else:
            self.other_fields.append(name)
            if not self.file_started:
                self.field = name
                self.fields.setdefault(name, b"")

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        if self.in_file:
            self.pending.append(bytes(data[start:end]))
        elif self.field is not None and len(self.fields[self.field]) < FIELD_BYTES:
            self.fields[self.field] = (self.fields[self.field] + bytes(data[start:end]))[:FIELD_BYTES]

    def on_part_end(self) -> None:
        self.field = None
        if self.in_file:
            self.in_file, self.file_ended = False, True

    def missing(self) -> FormError:
        if self.other_files:
            return FormError(f"the form sent a file in the field {self.other_files[0]!r}; send it in the field "
                             f"{FILE_FIELD!r}: {USAGE}", field=FILE_FIELD)
        fields = f" (it has {', '.join(repr(f) for f in self.other_fields)})" if self.other_fields else ""
        return FormError(f"the form has no field {FILE_FIELD!r}{fields}: {USAGE}", field=FILE_FIELD)


async def form_file(stream: AsyncIterator[bytes], content_type: str, limit: int,
                    fields: dict[str, str] | None = None) -> tuple[str | None, AsyncIterator[bytes]]:
    """(file name, chunks of the ``file`` part) of a multipart/form-data body.

    Reads until the file part's headers; FormError when there is none (naming the field to use)
    or the body is malformed, TooLargeError past ``limit`` bytes before it. ``fields``, when given,
    receives the text fields sent before the file part (their first KiB each).
    """
    _, params = parse_options_header(content_type)
    boundary = params.get(b"boundary")
    if not boundary:
        raise FormError(f"multipart/form-data without a boundary: let the client build the form, e.g. {USAGE}")
    if len(boundary) > MAX_BOUNDARY_LENGTH:  # the parser refuses it with its own error type (RFC 2046 says 70)
        raise FormError(f"multipart/form-data boundary of {len(boundary)} bytes, over the {MAX_BOUNDARY_LENGTH} "
                        f"the parser takes: let the client build the form, e.g. {USAGE}")
    parts = _Parts()
    parser = MultipartParser(boundary, parts.callbacks())  # type: ignore[arg-type]
    source = stream.__aiter__()
    read = 0

    def feed(chunk: bytes) -> None:
        try:
            parser.write(chunk)
        except MultipartParseError as err:
            raise FormError(f"malformed multipart/form-data body ({err}); send the file as {USAGE}") from None

    while not parts.file_started:
        try:
            chunk = await source.__anext__()
        except StopAsyncIteration:
            raise parts.missing() from None
        read += len(chunk)
        if read > limit:
            raise TooLargeError(f"upload is over the limit of {limit} bytes (SLAMREPLAY_MAX_UPLOAD_BYTES)")
        feed(chunk)
    if fields is not None:
        fields.update({k: v.decode("utf-8", "replace") for k, v in parts.fields.items()})

    async def chunks() -> AsyncIterator[bytes]:
        while True:
            if parts.pending:
                data = b"".join(parts.pending)
                parts.pending.clear()
                yield data
            if parts.file_ended:
                return
            try:
                chunk = await source.__anext__()
            except StopAsyncIteration:
                raise FormError(f"the form ended inside the {FILE_FIELD!r} part (an interrupted upload): "
                                f"send it again") from None
            feed(chunk)

    return parts.filename, chunks()
