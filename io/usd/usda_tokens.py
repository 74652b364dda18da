"""The tokens of an OpenUSD text layer, for usda_parse.py: strings, asset paths, numbers, words,
prim paths and punctuation, read one at a time from the layer's text.

Every pattern repeats possessively (`*+`): Python's regular expressions keep a backtracking entry
per repetition of a group otherwise, which costs about 150 bytes per character of a long string
literal. The text is never copied, and a string's escapes are decoded once, in C.
"""

import codecs
import re

from ..common import SplatFileError

STRING, ASSET, NUMBER, WORD, PATH, PUNCT = range(1, 7)

_TOKEN = re.compile(  # white space and comments, then one token: the number of its group is its kind
    r"(?:\s++|#[^\n]*+|//[^\n]*+|/\*(?:[^*]++|\*(?!/))*+\*/)*+"
    r'(?:("""|\'\'\'|"[^"\\\n]*+(?:\\.[^"\\\n]*+)*+"|\'[^\'\\\n]*+(?:\\.[^\'\\\n]*+)*+\')'
    r"|(@[^@\n]*+@)"
    r"|(-?+(?:\d++\.?+\d*+|\.\d++)(?:[eE][-+]?+\d++)?+(?![\w.])|-?+inf(?!\w)|nan(?!\w))"
    r"|([^\W\d][\w:.]*+(?:\[\])?+)"
    r"|(<[^<>\n]*+>)"
    r"|(\S))?"
)
_UNKNOWN_ESCAPE = re.compile(r"\\([^abfnrtvx0-7\\'\"\n])")


class Word(str):
    """A bare word of the text (a keyword such as `true`, or a name), as opposed to a quoted string."""


class Asset(str):
    """An asset path of the text (`@path@`)."""


class Tokens:
    """The tokens of `text` from `pos` on; failures are SplatFileErrors naming the file and line."""

    def __init__(self, path, text, pos=0):
        self.path, self.text, self.pos = path, text, pos
        self._peek_pos, self._peek = -1, None  # the last peek, kept: the parser peeks before it takes

    def fail(self, problem):
        line = self.text.count("\n", 0, self.pos) + 1
        raise SplatFileError(self.path, f"line {line}: {problem}")

    def peek(self):
        """(kind, token, end) of the next token; (None, None, end) at the end of the text."""
        if self._peek_pos == self.pos:
            return self._peek
        m = _TOKEN.match(self.text, self.pos)
        kind = m.lastindex
        if kind is None:
            found = (None, None, m.end())
        else:
            start, end = m.span(kind)
            if kind == STRING and end - start == 3 and self.text[start + 1] == self.text[start]:
                close = self.text.find(self.text[start:end], end)  # a triple-quoted string
                if close < 0:
                    self.pos = start
                    self.fail("a string in triple quotes is never closed")
                end = close + 3
            found = (kind, self.text[start:end], end)
        self._peek_pos, self._peek = self.pos, found
        return found

    def next(self, expected=None):
        """(kind, token) of the next token, consumed; it must be `expected` when one is given."""
        kind, tok, end = self.peek()
        if tok is None or (expected is not None and tok != expected):
            self._unexpected(tok, expected)
        self.pos = end
        return kind, tok

    def _unexpected(self, tok, expected):
        if tok is None:
            self.fail(f"unexpected end of file{f', expected {expected!r}' if expected else ''}")
        self.fail(f"expected {expected!r}, found {shown(tok)}")

    def at(self, tok):
        return self.peek()[1] == tok

    def string(self, tok):
        """The text a string token stands for, its escapes decoded as OpenUSD decodes them."""
        quote = 3 if len(tok) >= 6 and tok[:3] in ('"""', "'''") else 1
        body = tok[quote:-quote]
        if "\\" not in body:
            return body
        if _UNKNOWN_ESCAPE.search(body):
            body = _UNKNOWN_ESCAPE.sub(r"\1", body)  # "\q" stands for "q"
        try:
            return codecs.escape_decode(body.encode("utf-8"))[0].decode("utf-8", "replace")
        except ValueError as exc:
            self.fail(f"a string holds a bad escape: {exc}")


def shown(tok, limit=60):
    """A token as an error message quotes it: at most `limit` characters."""
    return repr(tok if len(tok) <= limit else tok[:limit] + "...")
