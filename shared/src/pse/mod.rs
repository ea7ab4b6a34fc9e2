//! The Pixel Stream Editor (Perlin 1985): a small language in which a scene
//! composes noise, turbulence and shaping functions per sample, in the papers'
//! notation, e.g. the 1989 fur:
//!
//! ```text
//! let s = noise(freq * project(x));
//! gain(0.9, bias(0.3, s)) * D(x)
//! ```
//!
//! Text is parsed ([`parser`]) and type-checked and compiled ([`compile`]) once, when
//! the scene is loaded, into register code ([`Program`], run by [`eval`]): straight
//! operations over a fixed register file and forward jumps only, so evaluation
//! always terminates, never allocates and cannot fail. Every error is found at
//! load, with the line and column inside the expression and a caret under the spot.

pub mod compile;
mod density;
pub mod eval;
pub mod fuzz;
pub mod lexer;
pub mod parser;
pub mod support;
pub mod surface;

pub use compile::{Context, Kind, compile_expression, parse_functions};
pub use eval::Program;
pub use surface::SceneExpressions;

/// A mistake in an expression, at a byte offset of its text.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ExprError {
    /// Byte offset in the expression text.
    pub at: usize,
    /// What is wrong and what was expected.
    pub message: String,
}

impl ExprError {
    /// An error at byte offset `at`.
    pub fn new(at: usize, message: impl Into<String>) -> ExprError {
        ExprError {
            at,
            message: message.into(),
        }
    }

    /// The 1-based line and column of the error in `src`.
    pub fn line_column(&self, src: &str) -> (usize, usize) {
        let at = floor_char_boundary(src, self.at);
        let before = &src[..at];
        let line = before.matches('\n').count() + 1;
        let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
        (line, column)
    }

    /// `line:column: message`, then the line of `src` and a caret under the spot.
    pub fn render(&self, src: &str) -> String {
        let (line, column) = self.line_column(src);
        let text = src.lines().nth(line - 1).unwrap_or("");
        format!(
            "{line}:{column}: {}\n    {text}\n    {}^",
            self.message,
            " ".repeat(column - 1)
        )
    }
}

/// A compile error of one of the scene's expressions, before it is located in the file.
#[derive(Clone, Debug, PartialEq)]
pub struct ExpressionFailure {
    /// The scene field.
    pub field: String,
    /// The expression text.
    pub source: String,
    /// What went wrong where.
    pub error: ExprError,
}

fn floor_char_boundary(s: &str, mut i: usize) -> usize {
    if i >= s.len() {
        return s.len();
    }
    while !s.is_char_boundary(i) {
        i -= 1;
    }
    i
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn caret_under_the_spot() {
        let e = ExprError::new(10, "unknown name `fre`");
        let src = "let s =\n  fre * 2;\n s";
        assert_eq!(e.line_column(src), (2, 3));
        assert_eq!(
            e.render(src),
            "2:3: unknown name `fre`\n      fre * 2;\n      ^"
        );
    }
}
