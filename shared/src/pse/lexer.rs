//! Tokens of the Pixel Stream Editor language.
//!
//! The lexer works on bytes of UTF-8 text; every token remembers the byte offset
//! where it starts so that errors can point at it.

use super::ExprError;

/// The longest expression text accepted (the whole scene is at most 64 KiB).
pub const MAX_SOURCE_BYTES: usize = 16 * 1024;

/// A token kind.
#[derive(Clone, Debug, PartialEq)]
pub enum Tok {
    /// A number literal.
    Num(f64),
    /// A name: variable, knob, function or keyword.
    Ident(String),
    /// An operator or punctuation mark, e.g. `+`, `<=`, `{`.
    Punct(&'static str),
    /// The end of the text.
    End,
}

/// A token and where it starts.
#[derive(Clone, Debug, PartialEq)]
pub struct Token {
    /// What it is.
    pub tok: Tok,
    /// Byte offset of its first character.
    pub at: usize,
}

const PUNCTS: [&str; 24] = [
    "<=", ">=", "==", "!=", "&&", "||", "+", "-", "*", "/", "%", "<", ">", "!", "(", ")", "[", "]",
    "{", "}", ",", ";", "=", ".",
];

/// Splits `src` into tokens, ending with [`Tok::End`].
pub fn tokenize(src: &str) -> Result<Vec<Token>, ExprError> {
    if src.len() > MAX_SOURCE_BYTES {
        return Err(ExprError::new(
            0,
            format!(
                "the expression is {} bytes; at most {MAX_SOURCE_BYTES} are allowed",
                src.len()
            ),
        ));
    }
    let bytes = src.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        let c = bytes[i];
        if c.is_ascii_whitespace() {
            i += 1;
            continue;
        }
        // Comments: `#` or `//` to the end of the line.
        if c == b'#' || (c == b'/' && bytes.get(i + 1) == Some(&b'/')) {
            while i < bytes.len() && bytes[i] != b'\n' {
                i += 1;
            }
            continue;
        }
        let start = i;
        if c.is_ascii_digit() || (c == b'.' && bytes.get(i + 1).is_some_and(u8::is_ascii_digit)) {
            while i < bytes.len() && (bytes[i].is_ascii_digit() || bytes[i] == b'.') {
                i += 1;
            }
            if i < bytes.len() && (bytes[i] == b'e' || bytes[i] == b'E') {
                let mut j = i + 1;
                if j < bytes.len() && (bytes[j] == b'+' || bytes[j] == b'-') {
                    j += 1;
                }
                if j < bytes.len() && bytes[j].is_ascii_digit() {
                    i = j;
                    while i < bytes.len() && bytes[i].is_ascii_digit() {
                        i += 1;
                    }
                }
            }
            let text = &src[start..i];
            let value: f64 = text
                .parse()
                .map_err(|_| ExprError::new(start, format!("`{text}` is not a number")))?;
            if !value.is_finite() {
                return Err(ExprError::new(start, format!("`{text}` is too large")));
            }
            out.push(Token {
                tok: Tok::Num(value),
                at: start,
            });
            continue;
        }
        if c.is_ascii_alphabetic() || c == b'_' {
            while i < bytes.len() && (bytes[i].is_ascii_alphanumeric() || bytes[i] == b'_') {
                i += 1;
            }
            out.push(Token {
                tok: Tok::Ident(src[start..i].to_string()),
                at: start,
            });
            continue;
        }
        let rest = &bytes[i..];
        match PUNCTS.iter().find(|p| rest.starts_with(p.as_bytes())) {
            Some(p) => {
                out.push(Token {
                    tok: Tok::Punct(p),
                    at: start,
                });
                i += p.len();
            }
            None => {
                let ch = src[start..].chars().next().unwrap_or('?');
                return Err(ExprError::new(
                    start,
                    format!("unexpected character `{ch}`"),
                ));
            }
        }
    }
    out.push(Token {
        tok: Tok::End,
        at: src.len(),
    });
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_and_offsets() {
        let t = tokenize("let s = 1.5e2 <= x.y; // c\n f(a)").unwrap();
        let kinds: Vec<_> = t.iter().map(|t| t.tok.clone()).collect();
        assert_eq!(kinds[0], Tok::Ident("let".into()));
        assert_eq!(kinds[3], Tok::Num(150.0));
        assert_eq!(kinds[4], Tok::Punct("<="));
        assert_eq!(t[1].at, 4);
        assert_eq!(kinds.last(), Some(&Tok::End));
        assert!(tokenize("1 $ 2").is_err());
        assert!(tokenize("1e999").is_err());
        assert!(tokenize("é").is_err());
    }
}
