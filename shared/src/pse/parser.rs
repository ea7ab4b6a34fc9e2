//! The grammar of the Pixel Stream Editor language, parsed by recursive descent
//! into an [`Expr`] tree.
//!
//! ```text
//! definitions := fndef*
//! fndef       := 'fn' NAME '(' [NAME (',' NAME)*] ')' '{' block '}'
//! block       := ('let' NAME '=' expr ';')* expr
//! expr        := or
//! or          := and ('||' and)*
//! and         := cmp ('&&' cmp)*
//! cmp         := add [('<' | '<=' | '>' | '>=' | '==' | '!=') add]
//! add         := mul (('+' | '-') mul)*
//! mul         := unary (('*' | '/' | '%') unary)*
//! unary       := ('-' | '!') unary | postfix
//! postfix     := primary ('.' ('x' | 'y' | 'z'))*
//! primary     := NUMBER | NAME | NAME '(' [expr (',' expr)*] ')' | '(' expr ')'
//!              | '[' expr ',' expr ',' expr ']' | if
//! if          := 'if' expr '{' block '}' 'else' ('{' block '}' | if)
//! ```
//!
//! Nesting depth and node count are capped so that no input can exhaust the stack
//! or the compile time.

use super::ExprError;
use super::lexer::{Tok, Token, tokenize};

/// Deepest nesting of sub-expressions.
pub const MAX_DEPTH: usize = 128;
/// Most syntax-tree nodes in one text.
pub const MAX_NODES: usize = 4096;

/// A unary operator.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UnOp {
    /// `-a`.
    Neg,
    /// `!a` (1 where a is 0, else 0).
    Not,
}

/// A binary operator.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BinOp {
    Add,
    Sub,
    Mul,
    Div,
    Rem,
    Lt,
    Le,
    Gt,
    Ge,
    Eq,
    Ne,
    And,
    Or,
}

impl BinOp {
    /// The operator as written.
    pub fn symbol(self) -> &'static str {
        match self {
            BinOp::Add => "+",
            BinOp::Sub => "-",
            BinOp::Mul => "*",
            BinOp::Div => "/",
            BinOp::Rem => "%",
            BinOp::Lt => "<",
            BinOp::Le => "<=",
            BinOp::Gt => ">",
            BinOp::Ge => ">=",
            BinOp::Eq => "==",
            BinOp::Ne => "!=",
            BinOp::And => "&&",
            BinOp::Or => "||",
        }
    }
}

/// An expression and the byte offset where it starts.
#[derive(Clone, Debug, PartialEq)]
pub struct Expr {
    /// What it is.
    pub kind: ExprKind,
    /// Byte offset in the source text.
    pub at: usize,
}

/// The kinds of expression.
#[derive(Clone, Debug, PartialEq)]
pub enum ExprKind {
    /// A number.
    Num(f64),
    /// A name: variable, knob, parameter or `let`.
    Var(String),
    /// `[a, b, c]`.
    Vector(Box<[Expr; 3]>),
    /// `f(args)`: a built-in, a soft object or a scene function.
    Call(String, Vec<Expr>),
    /// `op a`.
    Unary(UnOp, Box<Expr>),
    /// `a op b`.
    Binary(BinOp, Box<Expr>, Box<Expr>),
    /// `v.x`, `v.y`, `v.z` (0, 1, 2).
    Component(Box<Expr>, u8),
    /// `if c { a } else { b }`.
    If(Box<Expr>, Box<Block>, Box<Block>),
}

/// `let` bindings followed by the value.
#[derive(Clone, Debug, PartialEq)]
pub struct Block {
    /// `let name = value;` in order: (name, offset of the name, value).
    pub lets: Vec<(String, usize, Expr)>,
    /// The block's value.
    pub value: Expr,
}

/// A scene function: `fn name(a, b) { block }`.
#[derive(Clone, Debug, PartialEq)]
pub struct FnDef {
    /// Its name.
    pub name: String,
    /// Offset of the name.
    pub at: usize,
    /// Parameter names and their offsets.
    pub params: Vec<(String, usize)>,
    /// The body.
    pub body: Block,
    /// The text of all the definitions (offsets in errors refer to it).
    pub source: std::sync::Arc<str>,
}

const KEYWORDS: [&str; 4] = ["let", "if", "else", "fn"];

/// Parses an expression (a block: `let`s then a value).
pub fn parse_expression(src: &str) -> Result<Block, ExprError> {
    let mut p = Parser::new(src)?;
    let block = p.block()?;
    p.expect_end()?;
    Ok(block)
}

/// Parses a list of function definitions.
pub fn parse_definitions(src: &str) -> Result<Vec<FnDef>, ExprError> {
    let mut p = Parser::new(src)?;
    let source: std::sync::Arc<str> = src.into();
    let mut defs = Vec::new();
    while p.peek() != &Tok::End {
        defs.push(p.fndef(&source)?);
    }
    Ok(defs)
}

struct Parser {
    tokens: Vec<Token>,
    pos: usize,
    depth: usize,
    nodes: usize,
}

impl Parser {
    fn new(src: &str) -> Result<Parser, ExprError> {
        Ok(Parser {
            tokens: tokenize(src)?,
            pos: 0,
            depth: 0,
            nodes: 0,
        })
    }

    fn peek(&self) -> &Tok {
        &self.tokens[self.pos].tok
    }

    fn at(&self) -> usize {
        self.tokens[self.pos].at
    }

    fn bump(&mut self) -> Token {
        let t = self.tokens[self.pos].clone();
        if self.pos + 1 < self.tokens.len() {
            self.pos += 1;
        }
        t
    }

    fn describe(tok: &Tok) -> String {
        match tok {
            Tok::Num(v) => format!("the number {v}"),
            Tok::Ident(s) => format!("`{s}`"),
            Tok::Punct(p) => format!("`{p}`"),
            Tok::End => "the end of the expression".into(),
        }
    }

    fn unexpected(&self, expected: &str) -> ExprError {
        ExprError::new(
            self.at(),
            format!("expected {expected}, found {}", Self::describe(self.peek())),
        )
    }

    fn eat(&mut self, punct: &str) -> bool {
        if matches!(self.peek(), Tok::Punct(p) if *p == punct) {
            self.bump();
            true
        } else {
            false
        }
    }

    fn expect(&mut self, punct: &str) -> Result<(), ExprError> {
        if self.eat(punct) {
            Ok(())
        } else {
            Err(self.unexpected(&format!("`{punct}`")))
        }
    }

    fn eat_keyword(&mut self, kw: &str) -> bool {
        if matches!(self.peek(), Tok::Ident(s) if s == kw) {
            self.bump();
            true
        } else {
            false
        }
    }

    fn name(&mut self, what: &str) -> Result<(String, usize), ExprError> {
        match self.peek().clone() {
            Tok::Ident(s) if !KEYWORDS.contains(&s.as_str()) => {
                let at = self.bump().at;
                Ok((s, at))
            }
            _ => Err(self.unexpected(what)),
        }
    }

    fn expect_end(&self) -> Result<(), ExprError> {
        if self.peek() == &Tok::End {
            Ok(())
        } else {
            Err(self.unexpected("an operator or the end of the expression"))
        }
    }

    fn node(&mut self, kind: ExprKind, at: usize) -> Result<Expr, ExprError> {
        self.nodes += 1;
        if self.nodes > MAX_NODES {
            return Err(ExprError::new(
                at,
                format!("the expression has more than {MAX_NODES} parts"),
            ));
        }
        Ok(Expr { kind, at })
    }

    fn enter(&mut self) -> Result<(), ExprError> {
        self.depth += 1;
        if self.depth > MAX_DEPTH {
            return Err(ExprError::new(
                self.at(),
                format!("the expression is nested more than {MAX_DEPTH} deep"),
            ));
        }
        Ok(())
    }

    fn fndef(&mut self, source: &std::sync::Arc<str>) -> Result<FnDef, ExprError> {
        if !self.eat_keyword("fn") {
            return Err(self.unexpected("`fn`"));
        }
        let (name, at) = self.name("a function name")?;
        self.expect("(")?;
        let mut params = Vec::new();
        if !self.eat(")") {
            loop {
                params.push(self.name("a parameter name")?);
                if self.eat(")") {
                    break;
                }
                self.expect(",")?;
            }
        }
        self.expect("{")?;
        let body = self.block()?;
        self.expect("}")?;
        Ok(FnDef {
            name,
            at,
            params,
            body,
            source: std::sync::Arc::clone(source),
        })
    }

    fn block(&mut self) -> Result<Block, ExprError> {
        self.enter()?;
        let mut lets = Vec::new();
        while self.eat_keyword("let") {
            let (name, at) = self.name("a name after `let`")?;
            self.expect("=")?;
            let value = self.expr()?;
            self.expect(";")?;
            lets.push((name, at, value));
        }
        let value = self.expr()?;
        self.depth -= 1;
        Ok(Block { lets, value })
    }

    fn expr(&mut self) -> Result<Expr, ExprError> {
        self.enter()?;
        let e = self.or();
        self.depth -= 1;
        e
    }

    fn or(&mut self) -> Result<Expr, ExprError> {
        let depth = self.depth;
        let mut a = self.and()?;
        while matches!(self.peek(), Tok::Punct("||")) {
            self.enter()?;
            let at = self.bump().at;
            let b = self.and()?;
            a = self.node(ExprKind::Binary(BinOp::Or, Box::new(a), Box::new(b)), at)?;
        }
        self.depth = depth;
        Ok(a)
    }

    fn and(&mut self) -> Result<Expr, ExprError> {
        let depth = self.depth;
        let mut a = self.cmp()?;
        while matches!(self.peek(), Tok::Punct("&&")) {
            self.enter()?;
            let at = self.bump().at;
            let b = self.cmp()?;
            a = self.node(ExprKind::Binary(BinOp::And, Box::new(a), Box::new(b)), at)?;
        }
        self.depth = depth;
        Ok(a)
    }

    fn cmp(&mut self) -> Result<Expr, ExprError> {
        let a = self.add()?;
        let op = match self.peek() {
            Tok::Punct("<") => BinOp::Lt,
            Tok::Punct("<=") => BinOp::Le,
            Tok::Punct(">") => BinOp::Gt,
            Tok::Punct(">=") => BinOp::Ge,
            Tok::Punct("==") => BinOp::Eq,
            Tok::Punct("!=") => BinOp::Ne,
            _ => return Ok(a),
        };
        let at = self.bump().at;
        let b = self.add()?;
        self.node(ExprKind::Binary(op, Box::new(a), Box::new(b)), at)
    }

    fn add(&mut self) -> Result<Expr, ExprError> {
        let depth = self.depth;
        let mut a = self.mul()?;
        loop {
            let op = match self.peek() {
                Tok::Punct("+") => BinOp::Add,
                Tok::Punct("-") => BinOp::Sub,
                _ => {
                    self.depth = depth;
                    return Ok(a);
                }
            };
            self.enter()?;
            let at = self.bump().at;
            let b = self.mul()?;
            a = self.node(ExprKind::Binary(op, Box::new(a), Box::new(b)), at)?;
        }
    }

    fn mul(&mut self) -> Result<Expr, ExprError> {
        let depth = self.depth;
        let mut a = self.unary()?;
        loop {
            let op = match self.peek() {
                Tok::Punct("*") => BinOp::Mul,
                Tok::Punct("/") => BinOp::Div,
                Tok::Punct("%") => BinOp::Rem,
                _ => {
                    self.depth = depth;
                    return Ok(a);
                }
            };
            self.enter()?;
            let at = self.bump().at;
            let b = self.unary()?;
            a = self.node(ExprKind::Binary(op, Box::new(a), Box::new(b)), at)?;
        }
    }

    fn unary(&mut self) -> Result<Expr, ExprError> {
        let op = match self.peek() {
            Tok::Punct("-") => UnOp::Neg,
            Tok::Punct("!") => UnOp::Not,
            _ => return self.postfix(),
        };
        let at = self.bump().at;
        self.enter()?;
        let a = self.unary()?;
        self.depth -= 1;
        self.node(ExprKind::Unary(op, Box::new(a)), at)
    }

    fn postfix(&mut self) -> Result<Expr, ExprError> {
        let depth = self.depth;
        let mut e = self.primary()?;
        while self.eat(".") {
            let component = match self.peek() {
                Tok::Ident(s) if s == "x" => 0,
                Tok::Ident(s) if s == "y" => 1,
                Tok::Ident(s) if s == "z" => 2,
                _ => return Err(self.unexpected("`x`, `y` or `z` after `.`")),
            };
            let at = self.bump().at;
            self.enter()?;
            e = self.node(ExprKind::Component(Box::new(e), component), at)?;
        }
        self.depth = depth;
        Ok(e)
    }

    fn primary(&mut self) -> Result<Expr, ExprError> {
        let at = self.at();
        match self.peek().clone() {
            Tok::Num(v) => {
                self.bump();
                self.node(ExprKind::Num(v), at)
            }
            Tok::Punct("(") => {
                self.bump();
                let e = self.expr()?;
                self.expect(")")?;
                Ok(e)
            }
            Tok::Punct("[") => {
                self.bump();
                // A vector has exactly three components.
                let what = "`,` (a vector is [x, y, z])";
                let a = self.expr()?;
                if !self.eat(",") {
                    return Err(self.unexpected(what));
                }
                let b = self.expr()?;
                if !self.eat(",") {
                    return Err(self.unexpected(what));
                }
                let c = self.expr()?;
                if !self.eat("]") {
                    return Err(self.unexpected("`]` (a vector is [x, y, z])"));
                }
                self.node(ExprKind::Vector(Box::new([a, b, c])), at)
            }
            Tok::Ident(s) if s == "if" => self.if_else(),
            Tok::Ident(s) if !KEYWORDS.contains(&s.as_str()) => {
                self.bump();
                if self.eat("(") {
                    let mut args = Vec::new();
                    if !self.eat(")") {
                        loop {
                            args.push(self.expr()?);
                            if self.eat(")") {
                                break;
                            }
                            self.expect(",")?;
                        }
                    }
                    self.node(ExprKind::Call(s, args), at)
                } else {
                    self.node(ExprKind::Var(s), at)
                }
            }
            _ => Err(self.unexpected("a number, a name, `(`, `[` or `if`")),
        }
    }

    fn if_else(&mut self) -> Result<Expr, ExprError> {
        let at = self.bump().at; // `if`
        self.enter()?;
        let cond = self.expr()?;
        self.expect("{")?;
        let then = self.block()?;
        self.expect("}")?;
        if !self.eat_keyword("else") {
            return Err(self.unexpected("`else` (every `if` needs one: it is an expression)"));
        }
        let otherwise = if matches!(self.peek(), Tok::Ident(s) if s == "if") {
            let at = self.at();
            let e = self.if_else()?;
            Block {
                lets: Vec::new(),
                value: Expr { at, ..e },
            }
        } else {
            self.expect("{")?;
            let b = self.block()?;
            self.expect("}")?;
            b
        };
        self.depth -= 1;
        self.node(
            ExprKind::If(Box::new(cond), Box::new(then), Box::new(otherwise)),
            at,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn precedence() {
        let b = parse_expression("1 + 2 * 3 < 4 && !x").unwrap();
        let ExprKind::Binary(BinOp::And, lhs, _) = &b.value.kind else {
            panic!("{b:?}")
        };
        let ExprKind::Binary(BinOp::Lt, sum, _) = &lhs.kind else {
            panic!()
        };
        assert!(matches!(sum.kind, ExprKind::Binary(BinOp::Add, _, _)));
    }

    #[test]
    fn a_vector_needs_three_components() {
        let e = parse_expression("[1, 2]").unwrap_err();
        assert!(e.message.contains("a vector is [x, y, z]"), "{}", e.message);
        assert_eq!(e.at, 5);
        let e = parse_expression("[1, 2, 3, 4]").unwrap_err();
        assert!(
            e.message.contains("`]` (a vector is [x, y, z])"),
            "{}",
            e.message
        );
    }

    #[test]
    fn lets_if_components_and_definitions() {
        let b =
            parse_expression("let s = noise(x); if s > 0 { s } else if s < -1 { 0 } else { -s }.x")
                .unwrap();
        assert_eq!(b.lets.len(), 1);
        assert!(matches!(b.value.kind, ExprKind::Component(_, 0)));
        let defs = parse_definitions("fn f(a, b) { a + b } fn g() { 1 }").unwrap();
        assert_eq!(defs.len(), 2);
        assert_eq!(defs[0].params.len(), 2);
    }

    #[test]
    fn errors_point_at_the_spot() {
        let e = parse_expression("1 + * 2").unwrap_err();
        assert_eq!(e.at, 4);
        assert!(e.message.contains("expected a number"), "{}", e.message);
        let e = parse_expression("if x { 1 }").unwrap_err();
        assert!(e.message.contains("else"));
        let e = parse_expression("(1 + 2").unwrap_err();
        assert_eq!(e.at, 6);
        assert!(parse_expression("1 2").is_err());
        assert!(parse_expression("").is_err());
        assert!(parse_definitions("fn let() { 1 }").is_err());
    }

    #[test]
    fn depth_and_size_are_capped() {
        let deep = "(".repeat(1000) + "1" + &")".repeat(1000);
        assert!(
            parse_expression(&deep)
                .unwrap_err()
                .message
                .contains("nested")
        );
        let neg = "-".repeat(10_000) + "1";
        assert!(parse_expression(&neg).is_err());
        let long = vec!["1"; 5000].join("+");
        assert!(parse_expression(&long).is_err());
        let ok = vec!["1"; 100].join("+");
        assert!(parse_expression(&ok).is_ok());
    }
}
