"""Read a JSON document from a byte stream, holding only a little of its text at a time.

A submission is one object whose predictions fields map each token to 8 poses: tens of megabytes of text for
a navtest-size file, which `json.loads` would hold whole, with every number as a Python float in its lists.
This reader walks the document's own structure (the top object, a streamed field's object or list of objects)
and hands each member's value, read whole by the standard library's decoder (`JSONDecoder.raw_decode`: the
same scanner, so the same floats, bit for bit, and the same NaN and Infinity), to a `leaf` that makes it small
(the poses as an array) as soon as it is read. Objects are built by `object_pairs_hook`, as `json.loads` would
build them; the bytes are decoded as `json.loads` decodes bytes (its detection of UTF-8, -16 or -32, and
'surrogatepass'), a chunk at a time.

A value read whole that runs past the chunk it starts in may take at most `max_value_chars` characters: past
that the file is refused (a valid submission's values other than the streamed fields are a few hundred
characters of metadata), so what is held stays bounded whatever a file holds.
"""

from __future__ import annotations

import codecs
import json
import re
from collections.abc import Callable, Collection
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from scorer.submission import ByteSource

READ_BYTES = 1 << 16
_BLANK = re.compile(r"[ \t\n\r]*")


class JsonStreamError(ValueError):
    """Not valid JSON; the message says what and where, as `json.JSONDecodeError`'s does."""


class _Text:
    """The decoded text of a byte stream, read a chunk at a time; `pos` indexes `buf`, whose consumed start
    is dropped as it grows (what was dropped is kept as counts, for the positions of errors)."""

    def __init__(self, source: ByteSource) -> None:
        self.source = source
        start = source.read(4)  # what json.detect_encoding needs
        while len(start) < 4 and (more := source.read(4 - len(start))):
            start += more
        self.decoder = codecs.getincrementaldecoder(json.detect_encoding(start))("surrogatepass")
        self.buf, self.pos, self.eof = self.decoder.decode(start), 0, False
        self.dropped, self.dropped_lines, self.line_start = 0, 0, 0

    def fill(self) -> None:
        """Read the next chunk (or mark the end)."""
        if self.pos > READ_BYTES:
            gone = self.buf[: self.pos]
            self.dropped_lines += gone.count("\n")
            last = gone.rfind("\n")
            if last >= 0:
                self.line_start = self.dropped + last + 1
            self.dropped += self.pos
            self.buf, self.pos = self.buf[self.pos :], 0
        data = self.source.read(READ_BYTES)
        self.eof = not data
        self.buf += self.decoder.decode(data, final=self.eof)

    def error(self, message: str, pos: int | None = None) -> JsonStreamError:
        """Return the error `message` at `pos` of `buf`, placed as json.JSONDecodeError places it."""
        pos = self.pos if pos is None else pos
        line = self.dropped_lines + self.buf.count("\n", 0, pos) + 1
        newline = self.buf.rfind("\n", 0, pos)
        column = pos - newline if newline >= 0 else self.dropped + pos - self.line_start + 1
        return JsonStreamError(f"{message}: line {line} column {column} (char {self.dropped + pos})")

    def next_char(self) -> str:
        """Return the next character after blanks (not consumed); '' at the end."""
        while True:
            self.pos = _BLANK.match(self.buf, self.pos).end()  # type: ignore[union-attr]  # always matches
            if self.pos < len(self.buf) or self.eof:
                return self.buf[self.pos : self.pos + 1]
            self.fill()

    def expect(self, char: str, message: str) -> None:
        if self.next_char() != char:
            raise self.error(message)
        self.pos += 1

    def value(self, decoder: json.JSONDecoder, max_chars: int) -> Any:
        """Return the value at `pos` read whole (after blanks), reading on while it may continue."""
        self.next_char()
        while True:
            try:
                value, end = decoder.raw_decode(self.buf, self.pos)
            except json.JSONDecodeError as error:
                if self.eof:
                    raise self.error(error.msg, error.pos) from None
                end = len(self.buf)  # it may be cut by the chunk's end: read on
            if end < len(self.buf) or self.eof:  # a number at the very end may go on
                self.pos = end
                return value
            if len(self.buf) - self.pos > max_chars:
                raise self.error(f"a value longer than {max_chars:,} characters")
            self.fill()


class _Reader:
    """One document's walk: which fields are streamed, how leaves are kept, how objects are built."""

    def __init__(
        self,
        text: _Text,
        streamed: Collection[str],
        leaf: Callable[[Any], Any],
        object_pairs_hook: Callable[[list[tuple[str, Any]]], Any],
        max_value_chars: int,
    ) -> None:
        self.text, self.streamed, self.leaf, self.hook = text, streamed, leaf, object_pairs_hook
        self.max_chars = max_value_chars
        self.decoder = json.JSONDecoder(object_pairs_hook=object_pairs_hook)

    def whole(self) -> Any:
        return self.text.value(self.decoder, self.max_chars)

    def members(self, value_of: Callable[[str], Any]) -> Any:
        """Read an object whose '{' is next, each member's value by `value_of(key)`."""
        text = self.text
        text.expect("{", "Expecting value")
        pairs: list[tuple[str, Any]] = []
        if text.next_char() == "}":
            text.pos += 1
            return self.hook(pairs)
        while True:
            if text.next_char() != '"':
                raise text.error("Expecting property name enclosed in double quotes")
            key = self.whole()
            text.expect(":", "Expecting ':' delimiter")
            pairs.append((key, value_of(key)))
            if self.closed("}"):
                return self.hook(pairs)

    def streamed_value(self) -> Any:
        """A streamed field's value: an object of leaves, a list of them, or any value read whole."""
        text = self.text
        char = text.next_char()
        if char == "{":
            return self.members(lambda _: self.leaf(self.whole()))
        if char != "[":
            return self.whole()
        text.pos += 1
        items: list[Any] = []
        if text.next_char() == "]":
            text.pos += 1
            return items
        while True:
            items.append(self.streamed_value() if text.next_char() == "{" else self.whole())
            if self.closed("]"):
                return items

    def closed(self, close: str) -> bool:
        """Read what follows a member or an item: True at `close`, False at ',', else the decoder's error."""
        text = self.text
        char = text.next_char()
        if char != close and char != ",":
            raise text.error("Expecting ',' delimiter")
        text.pos += 1
        return char == close

    def document(self) -> Any:
        text = self.text
        if text.next_char() == "{":
            document = self.members(
                lambda key: self.streamed_value() if key in self.streamed else self.whole()
            )
        else:
            document = self.whole()
        if text.next_char():
            raise text.error("Extra data")
        return document


def read_json(
    source: ByteSource,
    streamed: Collection[str],
    leaf: Callable[[Any], Any],
    object_pairs_hook: Callable[[list[tuple[str, Any]]], Any],
    max_value_chars: int,
) -> Any:
    """Return the JSON document `source` reads, each member of a `streamed` top-level field's object (or
    list of objects) passed through `leaf` as soon as it is read. Raises JsonStreamError (a ValueError) for
    text that is not JSON, UnicodeDecodeError for bytes that are not text, RecursionError for nesting too deep
    for the standard decoder; the source's own errors pass through."""
    return _Reader(_Text(source), streamed, leaf, object_pairs_hook, max_value_chars).document()
