"""An upload's multipart/form-data body, read as it arrives: its small fields, and its one file as a stream.

Starlette's form parsing writes a file to a temporary file on the API's disk before a route runs (in full:
a 256 MiB upload takes 256 MiB of disk first). Here the route reads the body itself, through
python-multipart's push parser, a chunk at a time: the fields before the file are known when the file
starts (the phase, whose split bounds what the file may inflate to), the file's bytes are handed to the
reader (`read`) as they arrive, and the fields after it are read once the file has been read to its end.
"""

from __future__ import annotations

from collections.abc import Iterator

from python_multipart.exceptions import MultipartParseError
from python_multipart.multipart import MultipartParser, parse_options_header

from server.services.errors import Invalid

FILE_FIELD = "file"
FIELD_BYTES = 64 * 1024  # a form field (phase, method, authors, ...) is a line of text


def _refusal(message: str) -> Invalid:
    return Invalid(message, [{"token": None, "field": None, "message": message}])


class UploadForm:
    """The fields of a multipart body and, from `read`, its file field's bytes; `filename` once it starts."""

    def __init__(self, body: Iterator[bytes], content_type: str) -> None:
        kind, options = parse_options_header(content_type)
        boundary = options.get(b"boundary")
        if kind != b"multipart/form-data" or not boundary:
            raise _refusal("the upload must be a multipart/form-data body with a `file` field")
        self.fields: dict[str, str] = {}
        self.after_file: set[str] = set()  # the fields that came after the file
        self.filename: str | None = None
        self._body, self._ended = body, False
        self._name: str | None = None
        self._header_field, self._header_value = bytearray(), bytearray()
        self._value = bytearray()
        self._in_file, self._file_done = False, False
        self._pending = bytearray()
        self._parser = MultipartParser(
            boundary,
            {
                "on_part_begin": self._part_begin,
                "on_header_field": lambda data, start, end: self._header_field.extend(data[start:end]),
                "on_header_value": lambda data, start, end: self._header_value.extend(data[start:end]),
                "on_header_end": self._header_end,
                "on_headers_finished": self._headers_finished,
                "on_part_data": self._part_data,
                "on_part_end": self._part_end,
            },
        )

    def _part_begin(self) -> None:
        self._name, self._value = None, bytearray()

    def _header_end(self) -> None:
        if bytes(self._header_field).lower() == b"content-disposition":
            _, options = parse_options_header(bytes(self._header_value))
            self._name = options.get(b"name", b"").decode("utf-8", "replace")
            if self._name == FILE_FIELD:
                self.filename = options.get(b"filename", b"").decode("utf-8", "replace") or None
        self._header_field, self._header_value = bytearray(), bytearray()

    def _headers_finished(self) -> None:
        if self._name == FILE_FIELD:
            if self._file_done or self._in_file:
                raise _refusal("the form has more than one `file` field")
            self._in_file = True

    def _part_data(self, data: bytes, start: int, end: int) -> None:
        if self._name == FILE_FIELD:
            self._pending += data[start:end]
            return
        self._value += data[start:end]
        if len(self._value) > FIELD_BYTES:
            raise _refusal(f"form field {self._name!r} is longer than {FIELD_BYTES:,} bytes")

    def _part_end(self) -> None:
        if self._name == FILE_FIELD:
            self._in_file, self._file_done = False, True
        elif self._name:
            self.fields[self._name] = self._value.decode("utf-8", "replace")
            if self._file_done:
                self.after_file.add(self._name)

    def _feed(self) -> bool:
        """Parse the body's next chunk; return False at its end."""
        if self._ended:
            return False
        try:
            for chunk in self._body:
                if chunk:
                    self._parser.write(chunk)
                    return True
            self._ended = True
            self._parser.finalize()
        except MultipartParseError as error:
            raise _refusal(f"the upload is not a well-formed multipart/form-data body: {error}") from None
        return False

    def start_file(self) -> None:
        """Read the fields before the file, up to its first bytes; Invalid when the body has no file field."""
        while not (self._in_file or self._file_done) and self._feed():
            pass
        if not (self._in_file or self._file_done):
            raise _refusal("the form has no `file` field")

    def read(self, size: int = -1) -> bytes:
        """Return at most `size` bytes of the file as they arrive (b'' at its end, once the whole body, the
        fields after the file included, has been read)."""
        while not self._pending and self._feed():
            pass
        size = len(self._pending) if size < 0 else size
        data = bytes(self._pending[:size])
        del self._pending[:size]
        return data
