//! RON's lexical pieces that a scanner of scene text steps over: comments
//! (line, and nested block comments), strings, raw strings and character
//! literals. Each function takes the offset where the piece starts and gives
//! the offset just after it. The scene's diagnostics and the studio's number
//! scanner read the text with them, so both skip what `ron` skips.

/// The byte offset just after the string literal starting at `at` (a `"`);
/// `None` when it is not closed.
pub fn string_end(text: &str, at: usize) -> Option<usize> {
    let bytes = text.as_bytes();
    let mut i = at + 1;
    while i < bytes.len() {
        match bytes[i] {
            b'\\' => i += 2,
            b'"' => return Some(i + 1),
            _ => i += 1,
        }
    }
    None
}

/// The end of the line comment starting at `at` (its newline, or the end).
pub fn line_comment_end(bytes: &[u8], at: usize) -> usize {
    let mut i = at;
    while i < bytes.len() && bytes[i] != b'\n' {
        i += 1;
    }
    i
}

/// Just after the block comment starting at `at` (RON's nest), or the end.
pub fn block_comment_end(bytes: &[u8], at: usize) -> usize {
    let mut depth = 0usize;
    let mut i = at;
    while i < bytes.len() {
        if bytes[i..].starts_with(b"/*") {
            depth += 1;
            i += 2;
        } else if bytes[i..].starts_with(b"*/") {
            depth -= 1;
            i += 2;
            if depth == 0 {
                break;
            }
        } else {
            i += 1;
        }
    }
    i
}

/// Just after the raw string (`r"…"`, `r#"…"#`) starting at `at` (or the
/// end of the text when it is not closed); `None` when the `r` and its `#`s
/// are not followed by `"`.
pub fn raw_string_end(bytes: &[u8], at: usize) -> Option<usize> {
    let hashes = bytes[at + 1..].iter().take_while(|&&c| c == b'#').count();
    if bytes.get(at + 1 + hashes) != Some(&b'"') {
        return None;
    }
    let close: Vec<u8> = std::iter::once(b'"')
        .chain(std::iter::repeat_n(b'#', hashes))
        .collect();
    let start = at + 2 + hashes;
    Some(
        bytes[start..]
            .windows(close.len())
            .position(|w| w == close.as_slice())
            .map_or(bytes.len(), |p| start + p + close.len()),
    )
}

/// Just after the character literal starting at `at`: `'x'` or `'\n'`.
pub fn char_literal_end(text: &str, at: usize) -> usize {
    let bytes = text.as_bytes();
    let end = if bytes.get(at + 1) == Some(&b'\\') {
        at + 4
    } else {
        at + 1 + text[at + 1..].chars().next().map_or(0, char::len_utf8) + 1
    };
    end.min(bytes.len())
}
