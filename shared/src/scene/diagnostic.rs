//! Scene errors in the scene's own words: the field a bad value stands in and
//! what was found there, the scene's names for its kinds of things (never the
//! program's type names), and an unclosed bracket at the place it was opened.

use ron::error::Error;

use super::ron_text::{
    block_comment_end, char_literal_end, line_comment_end, raw_string_end, string_end,
};

/// A position in the text as a byte offset.
type Offset = usize;

/// Where to point and what to say for `ron`'s error `code` at `offset` of
/// `text`: a value of the wrong type is pointed at itself (`ron` points at the
/// space before it).
pub(crate) fn message(code: &Error, text: &str, offset: Offset) -> (Offset, String) {
    let value = |offset: Offset| {
        let rest = text.get(offset..).unwrap_or("");
        offset + rest.len() - rest.trim_start().len()
    };
    match code {
        Error::ExpectedFloat
        | Error::ExpectedInteger
        | Error::ExpectedString
        | Error::ExpectedBoolean
        | Error::ExpectedArray
        | Error::ExpectedMap
        | Error::ExpectedStructLike
        | Error::ExpectedNamedStructLike(_)
        | Error::InvalidValueForType { .. } => (value(offset), words(code, text, offset)),
        _ => (offset, words(code, text, offset)),
    }
}

fn words(code: &Error, text: &str, offset: Offset) -> String {
    let field = || field_path(text, offset);
    let found = || found_at(text, offset);
    let one_of = |names: &[&str]| {
        let names: Vec<String> = names.iter().map(|n| format!("`{n}`")).collect();
        match names.len() {
            0 => "none is allowed here".to_string(),
            1 => format!("expected {}", names[0]),
            _ => format!("expected one of {}", names.join(", ")),
        }
    };
    let expected = |what: &str| match field() {
        Some(field) => format!("{field}: expected {what}, found {}", found()),
        None => format!("expected {what}, found {}", found()),
    };
    match code {
        Error::ExpectedFloat => expected("a number"),
        Error::ExpectedInteger => expected("a whole number"),
        Error::ExpectedString => expected("a string"),
        Error::ExpectedBoolean => expected("`true` or `false`"),
        Error::ExpectedArray => expected("a list `[…]`"),
        Error::ExpectedMap => expected("a map `{…}`"),
        Error::ExpectedStructLike => expected("`(`"),
        Error::ExpectedNamedStructLike(name) => expected(&format!("`(` opening {}", word(name))),
        Error::InvalidValueForType { expected: what, .. } => expected(&type_word(what)),
        Error::NoSuchEnumVariant {
            expected,
            found,
            outer,
        } => format!(
            "unknown {} `{found}`, {}",
            outer.as_deref().map_or_else(|| "kind".to_string(), word),
            one_of(expected)
        ),
        Error::NoSuchStructField {
            expected,
            found,
            outer,
        } => format!(
            "unknown field `{found}`{}, {}",
            in_outer(outer),
            one_of(expected)
        ),
        Error::MissingStructField { field, outer } => {
            format!("missing field `{field}`{}", in_outer(outer))
        }
        Error::DuplicateStructField { field, outer } => {
            format!("field `{field}` given twice{}", in_outer(outer))
        }
        Error::ExpectedDifferentStructName { expected, found } => {
            format!("expected {}, found `{found}`", word(expected))
        }
        Error::ExpectedStructName(name) => format!("expected {} here", word(name)),
        other => other.to_string(),
    }
}

fn in_outer(outer: &Option<String>) -> String {
    outer
        .as_deref()
        .map_or_else(String::new, |o| format!(" in {}", word(o)))
}

/// The scene's word for a type's name: `DmfDesc` → `modulation`,
/// `ColourIndexDesc` → `colour index`, `SphereFields` (renamed `Sphere`) → `sphere`.
pub(crate) fn word(name: &str) -> String {
    let stem = name
        .strip_suffix("Desc")
        .or_else(|| name.strip_suffix("Fields"))
        .unwrap_or(name);
    match stem {
        "Dmf" => return "modulation".into(),
        "Transfer" => return "transfer function".into(),
        "Scene" => return "the scene".into(),
        "Map" => return "curve".into(),
        _ => {}
    }
    let mut out = String::new();
    for (i, c) in stem.chars().enumerate() {
        if c.is_uppercase() && i > 0 {
            out.push(' ');
        }
        out.extend(c.to_lowercase());
    }
    out
}

/// Serde's name of a primitive type as a reader says it.
fn type_word(name: &str) -> String {
    match name {
        "f32" | "f64" | "a float" => "a number".into(),
        "u8" | "u16" | "u32" | "u64" | "i32" | "i64" | "an integer" => "a whole number".into(),
        "a string" | "str" | "string" => "a string".into(),
        other => word(other),
    }
}

/// What stands at `offset`: `the string "big"`, `` `Sphere` ``, `the number 3`, `a `(``.
fn found_at(text: &str, offset: Offset) -> String {
    let rest = text.get(offset..).unwrap_or("").trim_start();
    let Some(first) = rest.chars().next() else {
        return "the end of the file".into();
    };
    if first == '"' {
        let end = string_end(rest, 0).unwrap_or(rest.len());
        return format!("the string {}", &rest[..end]);
    }
    if first.is_alphanumeric() || first == '_' || first == '-' || first == '+' || first == '.' {
        let token: String = rest
            .chars()
            .take_while(|c| c.is_alphanumeric() || matches!(c, '_' | '-' | '+' | '.'))
            .collect();
        if token.parse::<f64>().is_ok() {
            return format!("the number {token}");
        }
        return format!("`{token}`");
    }
    format!("`{first}`")
}

/// One open bracket while scanning.
struct Open {
    /// `(`, `[` or `{`.
    bracket: u8,
    /// Where it is.
    at: Offset,
    /// The field being given inside it (`radius`), if any.
    field: Option<String>,
    /// The element's index, counting commas.
    index: usize,
}

/// What [`scan`] found.
enum Scan {
    /// The whole text: every bracket closed.
    Balanced,
    /// Stopped at `offset`: the path of fields to it.
    Path(Vec<String>),
    /// A bracket opened at this offset is never closed (or closed by the wrong one).
    Unclosed(Offset, u8),
    /// A closing bracket at this offset closes nothing.
    Unopened(Offset, u8),
}

/// Walks the text as RON reads it (strings, raw strings, characters, nested
/// block comments, line comments), to `stop` or the end.
fn scan(text: &str, stop: Option<Offset>) -> Scan {
    let bytes = text.as_bytes();
    let mut scanner = Scanner {
        text,
        stack: Vec::new(),
        last_ident: None,
        last_string: None,
    };
    let mut i = 0;
    while i < bytes.len() {
        if stop.is_some_and(|s| i >= s) {
            break;
        }
        if let Some(end) = scanner.skip_literal(i) {
            i = end;
            continue;
        }
        match bytes[i] {
            b @ (b'(' | b'[' | b'{') => scanner.open(b, i),
            b @ (b')' | b']' | b'}') => {
                if let Err(unbalanced) = scanner.close(b, i) {
                    return unbalanced;
                }
            }
            b',' => scanner.comma(),
            b':' => scanner.colon(),
            c if c.is_ascii_alphabetic() || c == b'_' => {
                i = scanner.ident(i);
                continue;
            }
            c if c.is_ascii_whitespace() => {}
            _ => {
                scanner.last_ident = None;
                scanner.last_string = None;
            }
        }
        i += 1;
    }
    scanner.finish(stop)
}

/// What [`scan`] has seen so far: the open brackets, and the identifier or
/// string just read (a field's name when a `:` follows).
struct Scanner<'a> {
    text: &'a str,
    stack: Vec<Open>,
    last_ident: Option<(Offset, Offset)>,
    last_string: Option<(Offset, Offset)>,
}

impl Scanner<'_> {
    /// Steps over the comment, string, raw string or character literal at
    /// `i`: where it ends, or `None` when none starts there. (An `r#` that
    /// opens no raw string is stepped over by its `r`.)
    fn skip_literal(&mut self, i: Offset) -> Option<Offset> {
        let bytes = self.text.as_bytes();
        match bytes[i] {
            b'/' if bytes.get(i + 1) == Some(&b'/') => Some(line_comment_end(bytes, i)),
            b'/' if bytes.get(i + 1) == Some(&b'*') => Some(block_comment_end(bytes, i)),
            b'"' => {
                let end = string_end(self.text, i).unwrap_or(bytes.len());
                self.last_string = Some((i, end));
                self.last_ident = None;
                Some(end)
            }
            b'r' if matches!(bytes.get(i + 1), Some(b'"' | b'#')) => match raw_string_end(bytes, i)
            {
                Some(end) => {
                    self.last_ident = None;
                    Some(end)
                }
                None => Some(i + 1),
            },
            b'\'' => Some(char_literal_end(self.text, i)),
            _ => None,
        }
    }

    fn open(&mut self, bracket: u8, at: Offset) {
        self.stack.push(Open {
            bracket,
            at,
            field: None,
            index: 0,
        });
        self.last_ident = None;
    }

    /// Closes the innermost bracket; the imbalance when `bracket` closes
    /// nothing or another kind.
    fn close(&mut self, bracket: u8, at: Offset) -> Result<(), Scan> {
        let want = match bracket {
            b')' => b'(',
            b']' => b'[',
            _ => b'{',
        };
        match self.stack.pop() {
            None => return Err(Scan::Unopened(at, bracket)),
            Some(open) if open.bracket != want => {
                return Err(Scan::Unclosed(open.at, open.bracket));
            }
            Some(_) => {}
        }
        self.last_ident = None;
        Ok(())
    }

    fn comma(&mut self) {
        if let Some(top) = self.stack.last_mut() {
            top.index += 1;
            top.field = None;
        }
        self.last_ident = None;
    }

    /// A `:` names the current element's field after the identifier (or the
    /// map key string) before it.
    fn colon(&mut self) {
        let text = self.text;
        let name = self
            .last_ident
            .map(|(s, e)| text[s..e].to_string())
            .or_else(|| self.last_string.map(|(s, e)| text[s..e].to_string()));
        if let (Some(top), Some(name)) = (self.stack.last_mut(), name) {
            top.field = Some(name);
        }
        self.last_ident = None;
    }

    /// Reads the identifier starting at `start`; where it ends.
    fn ident(&mut self, start: Offset) -> Offset {
        let bytes = self.text.as_bytes();
        let mut i = start;
        while i < bytes.len() && (bytes[i].is_ascii_alphanumeric() || bytes[i] == b'_') {
            i += 1;
        }
        self.last_ident = Some((start, i));
        self.last_string = None;
        i
    }

    /// The path to the stopping point, or whether every bracket closed.
    fn finish(mut self, stop: Option<Offset>) -> Scan {
        if stop.is_some() {
            // The outermost bracket is the scene itself: its fields lead the path.
            let mut names = Vec::new();
            for (depth, open) in self.stack.iter().enumerate() {
                match &open.field {
                    Some(field) => names.push(field.clone()),
                    None if depth > 0 => names.push(format!("[{}]", open.index)),
                    None => {}
                }
            }
            return Scan::Path(names);
        }
        match self.stack.pop() {
            Some(open) => Scan::Unclosed(open.at, open.bracket),
            None => Scan::Balanced,
        }
    }
}

/// The fields leading to `offset`: `object.radius`, `modulation[1].amount`,
/// `camera.eye[2]`.
fn field_path(text: &str, offset: Offset) -> Option<String> {
    let Scan::Path(names) = scan(text, Some(offset)) else {
        return None;
    };
    let mut path = String::new();
    for name in names {
        if !name.starts_with('[') && !path.is_empty() {
            path.push('.');
        }
        path.push_str(&name);
    }
    (!path.is_empty()).then_some(path)
}

/// An unbalanced bracket as (offset, message), before `ron` would report it
/// somewhere further down: an unclosed one at the place it was opened.
pub(crate) fn check_brackets(text: &str) -> Option<(Offset, String)> {
    match scan(text, None) {
        Scan::Balanced | Scan::Path(_) => None,
        Scan::Unclosed(at, bracket) => {
            let at = likely_unclosed(text).unwrap_or(at);
            let bracket = text.as_bytes().get(at).copied().unwrap_or(bracket);
            Some((
                at,
                format!(
                    "unclosed `{}`: opened here and never closed",
                    bracket as char
                ),
            ))
        }
        Scan::Unopened(at, bracket) => {
            Some((at, format!("`{}` closes no open bracket", bracket as char)))
        }
    }
}

/// In text laid out line by line, the bracket left open: the one whose line is
/// indented deeper than the first closing bracket that starts a line and
/// closes it.
fn likely_unclosed(text: &str) -> Option<Offset> {
    let indent = |at: Offset| {
        let line_start = text[..at].rfind('\n').map_or(0, |n| n + 1);
        text[line_start..]
            .bytes()
            .take_while(|b| *b == b' ' || *b == b'\t')
            .count()
    };
    let starts_line = |at: Offset| {
        let line_start = text[..at].rfind('\n').map_or(0, |n| n + 1);
        text[line_start..at].trim().is_empty()
    };
    // Pair the brackets (strings and comments skipped by `scan`'s rules).
    let mut stack: Vec<Offset> = Vec::new();
    let mut pos = 0;
    while pos < text.len() {
        let Some(next) = next_bracket(text, pos) else {
            break;
        };
        let b = text.as_bytes()[next];
        if matches!(b, b'(' | b'[' | b'{') {
            stack.push(next);
        } else if let Some(open) = stack.pop()
            && starts_line(next)
            && indent(next) < indent(open)
            && text[..next].matches('\n').count() > text[..open].matches('\n').count()
        {
            return Some(open);
        }
        pos = next + 1;
    }
    None
}

/// The offset of the next bracket at or after `from` outside strings and comments.
fn next_bracket(text: &str, from: Offset) -> Option<Offset> {
    let mut i = from;
    let bytes = text.as_bytes();
    while i < bytes.len() {
        match bytes[i] {
            b'/' if bytes.get(i + 1) == Some(&b'/') => i = line_comment_end(bytes, i),
            b'/' if bytes.get(i + 1) == Some(&b'*') => i = block_comment_end(bytes, i),
            b'"' => i = string_end(text, i).unwrap_or(bytes.len()),
            b'(' | b'[' | b'{' | b')' | b']' | b'}' => return Some(i),
            _ => i += 1,
        }
    }
    None
}

/// The 1-based (line, column) of `offset`.
pub(crate) fn line_column(text: &str, offset: Offset) -> (usize, usize) {
    let before = &text[..offset.min(text.len())];
    let line = before.matches('\n').count() + 1;
    let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
    (line, column)
}

/// The byte offset of the 1-based (line, column) `ron` reports.
pub(crate) fn offset_of(text: &str, line: usize, column: usize) -> Offset {
    let line_start = text
        .split_inclusive('\n')
        .take(line.saturating_sub(1))
        .map(str::len)
        .sum::<usize>();
    let rest = &text[line_start.min(text.len())..];
    line_start
        + rest
            .char_indices()
            .nth(column.saturating_sub(1))
            .map_or(rest.len(), |(i, _)| i)
}
