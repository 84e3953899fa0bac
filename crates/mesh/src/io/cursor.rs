//! A byte cursor shared by the text and binary parsers. It never panics on any input:
//! every read is bounds-checked and reports the byte offset where it failed.

use std::str::FromStr;

/// A parse failure at a byte offset; the caller turns it into a [`super::ReadError`]
/// with the path and the line number.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct ParseError {
    pub offset: usize,
    pub kind: ParseErrorKind,
}

#[derive(Debug, Clone, PartialEq)]
pub(crate) enum ParseErrorKind {
    /// Something else stood where `expected` should.
    Expected { expected: String, found: String },
    /// A well-formed feature the reader does not support.
    Unsupported(String),
}

impl ParseError {
    pub fn expected(offset: usize, expected: impl Into<String>, found: impl Into<String>) -> Self {
        Self {
            offset,
            kind: ParseErrorKind::Expected {
                expected: expected.into(),
                found: found.into(),
            },
        }
    }

    pub fn unsupported(offset: usize, what: impl Into<String>) -> Self {
        Self {
            offset,
            kind: ParseErrorKind::Unsupported(what.into()),
        }
    }
}

pub(crate) type Parse<T> = Result<T, ParseError>;

/// Shows at most a few dozen characters of what was found, escaped.
pub(crate) fn show(bytes: &[u8]) -> String {
    if bytes.is_empty() {
        return "end of file".to_owned();
    }
    let cut = &bytes[..bytes.len().min(40)];
    let mut s = format!("{:?}", String::from_utf8_lossy(cut));
    if bytes.len() > 40 {
        s.push_str("...");
    }
    s
}

pub(crate) struct Cursor<'a> {
    data: &'a [u8],
    pos: usize,
    /// Start of a comment that runs to the end of the line (TetGen's `#`).
    comment: Option<u8>,
    /// Byte order of binary sections: true when the file's order differs from little-endian.
    pub swap: bool,
}

impl<'a> Cursor<'a> {
    pub fn new(data: &'a [u8], comment: Option<u8>) -> Self {
        Self {
            data,
            pos: 0,
            comment,
            swap: false,
        }
    }

    pub fn offset(&self) -> usize {
        self.pos
    }

    /// Offset of the next token (skips blanks and comments); for text formats only.
    pub fn here(&mut self) -> usize {
        self.skip_space();
        self.pos
    }

    pub fn remaining(&self) -> usize {
        self.data.len() - self.pos
    }

    fn skip_space(&mut self) {
        while let Some(&b) = self.data.get(self.pos) {
            if b.is_ascii_whitespace() {
                self.pos += 1;
            } else if Some(b) == self.comment {
                while self.data.get(self.pos).is_some_and(|&c| c != b'\n') {
                    self.pos += 1;
                }
            } else {
                break;
            }
        }
    }

    /// Skips blanks and comments up to the next token without consuming it; `None` at end.
    pub fn peek_token(&mut self) -> Option<&'a [u8]> {
        self.skip_space();
        let start = self.pos;
        let end = self.data[start..]
            .iter()
            .position(|b| b.is_ascii_whitespace() || Some(*b) == self.comment)
            .map_or(self.data.len(), |k| start + k);
        (end > start).then(|| &self.data[start..end])
    }

    /// The next whitespace-separated token, or an error naming `what` at end of input.
    pub fn token(&mut self, what: &str) -> Parse<&'a [u8]> {
        match self.peek_token() {
            Some(t) => {
                self.pos += t.len();
                Ok(t)
            }
            None => Err(ParseError::expected(self.pos, what, "end of file")),
        }
    }

    /// Consumes a token equal to `keyword`.
    pub fn keyword(&mut self, keyword: &str) -> Parse<()> {
        self.skip_space();
        let at = self.pos;
        let t = self.token(keyword)?;
        if t == keyword.as_bytes() {
            Ok(())
        } else {
            Err(ParseError::expected(at, format!("`{keyword}`"), show(t)))
        }
    }

    /// Parses the next token as `T`.
    pub fn parse<T: FromStr>(&mut self, what: &str) -> Parse<T> {
        self.skip_space();
        let at = self.pos;
        let t = self.token(what)?;
        std::str::from_utf8(t)
            .ok()
            .and_then(|s| s.parse().ok())
            .ok_or_else(|| ParseError::expected(at, what, show(t)))
    }

    /// The rest of the current line (without the newline), consuming the newline.
    pub fn line(&mut self) -> &'a [u8] {
        let start = self.pos;
        let end = self.data[start..]
            .iter()
            .position(|&b| b == b'\n')
            .map_or(self.data.len(), |k| start + k);
        self.pos = (end + 1).min(self.data.len());
        let line = &self.data[start..end];
        line.strip_suffix(b"\r").unwrap_or(line)
    }

    /// Skips spaces and tabs then exactly one line end, as before a binary block.
    pub fn end_of_line(&mut self) -> Parse<()> {
        while matches!(self.data.get(self.pos), Some(b' ' | b'\t' | b'\r')) {
            self.pos += 1;
        }
        match self.data.get(self.pos) {
            Some(b'\n') => {
                self.pos += 1;
                Ok(())
            }
            _ => Err(ParseError::expected(
                self.pos,
                "end of line",
                show(&self.data[self.pos..]),
            )),
        }
    }

    /// Skips everything up to and including the token `keyword` at the start of a line.
    pub fn skip_to(&mut self, keyword: &str) -> Parse<()> {
        let needle = keyword.as_bytes();
        let mut k = self.pos;
        while k + needle.len() <= self.data.len() {
            if &self.data[k..k + needle.len()] == needle && (k == 0 || self.data[k - 1] == b'\n') {
                self.pos = k + needle.len();
                return Ok(());
            }
            k += 1;
        }
        Err(ParseError::expected(
            self.pos,
            format!("`{keyword}`"),
            "end of file",
        ))
    }

    /// `n` raw bytes.
    pub fn bytes(&mut self, n: usize, what: &str) -> Parse<&'a [u8]> {
        if n > self.remaining() {
            return Err(ParseError::expected(
                self.pos,
                format!("{what} ({n} bytes)"),
                format!("end of file after {} bytes", self.remaining()),
            ));
        }
        let out = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(out)
    }

    fn array<const N: usize>(&mut self, what: &str) -> Parse<[u8; N]> {
        let mut a: [u8; N] = self.bytes(N, what)?.try_into().expect("length checked");
        if self.swap {
            a.reverse();
        }
        Ok(a)
    }

    pub fn i32(&mut self, what: &str) -> Parse<i32> {
        self.array::<4>(what).map(i32::from_le_bytes)
    }

    pub fn f64(&mut self, what: &str) -> Parse<f64> {
        self.array::<8>(what).map(f64::from_le_bytes)
    }

    /// An unsigned integer of `size` bytes (4 or 8), Gmsh's `size_t`.
    pub fn unsigned(&mut self, size: usize, what: &str) -> Parse<u64> {
        if size == 4 {
            self.array::<4>(what)
                .map(|a| u64::from(u32::from_le_bytes(a)))
        } else {
            self.array::<8>(what).map(u64::from_le_bytes)
        }
    }
}

/// 1-based line number of byte `offset` in `data`.
pub(crate) fn line_of(data: &[u8], offset: usize) -> usize {
    1 + data[..offset.min(data.len())]
        .iter()
        .filter(|&&b| b == b'\n')
        .count()
}
