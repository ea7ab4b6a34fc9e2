//! The numbers of a scene's text, found where they stand, so that the studio
//! can give each numeric parameter of the object, its modulations, the
//! distortion, the camera and the lights a slider, and each control point of
//! a curve (colour and alpha maps, 1D shape transfer functions) a handle, and
//! write a moved value back into the text without touching anything else.
//!
//! A number's *path* names it by the fields, variants and positions that lead
//! to it: `object.Torus.minor_radius`, `camera.eye[1]`,
//! `modulation[0].Fur.frequency`, `alpha_map.points[1][0]`. Paths are stable
//! while only numbers change, so a slider keeps its identity as it moves.
//!
//! The scanner reads RON's shape only (brackets, `name:`, commas, comments,
//! strings); the scene parser still decides whether the text is a scene.

use std::collections::BTreeMap;

use hypertexture::scene::ron_text;
use serde::Serialize;

/// A number in the text.
#[derive(Clone, Debug, PartialEq)]
pub struct Number {
    pub path: String,
    pub value: f64,
    /// Written without a point or exponent.
    pub integer: bool,
    /// Its bytes in the text.
    pub span: std::ops::Range<usize>,
    /// The scene's own words on it: see [`comment_of`].
    pub comment: String,
}

/// One open bracket while scanning.
struct Level {
    /// The path up to and including this bracket's own segment.
    path: String,
    /// Where the bracket stands in the text.
    at: usize,
    /// Position among the bracket's comma-separated items.
    index: usize,
    /// The `name:` seen for the current item.
    key: Option<String>,
    /// Where the current item's first token starts, and its value's (after
    /// its `name:`), and where its last token so far ends.
    item_start: Option<usize>,
    value_start: Option<usize>,
    last_end: usize,
}

/// An item of a bracket as it stands in the text: a field (`name: value`) or
/// a list's element.
#[derive(Clone, Debug, PartialEq)]
pub struct Item {
    /// Its path (as a number in it is named: `alpha_map.points[1]`,
    /// `distortion.terms[0].operator`).
    pub path: String,
    /// The path of the bracket it stands in.
    pub parent: String,
    /// From its first token (its name, if it has one) to the end of its value.
    pub span: std::ops::Range<usize>,
    /// Its value's bytes.
    pub value: std::ops::Range<usize>,
}

/// What a scan finds in a scene's text: its numbers, the bare words given as
/// a field's value by the field's path, and every item of every bracket.
pub struct Scanned {
    pub numbers: Vec<Number>,
    pub words: BTreeMap<String, String>,
    pub items: Vec<Item>,
}

/// The numbers, words and items of `text`, in the order they stand.
pub fn scanned(text: &str) -> Scanned {
    let s = scan(text);
    Scanned {
        numbers: s.out,
        words: s.words,
        items: s.items,
    }
}

impl Level {
    /// The segment of the current item: its field name, or its position.
    fn item(&self) -> String {
        match &self.key {
            Some(k) => join(&self.path, k),
            None => format!("{}[{}]", self.path, self.index),
        }
    }
}

fn join(path: &str, segment: &str) -> String {
    if path.is_empty() {
        segment.to_string()
    } else {
        format!("{path}.{segment}")
    }
}

/// Every number in `text` with its path, in the order they stand. Numbers in
/// comments and strings are not numbers of the scene.
pub fn numbers(text: &str) -> Vec<Number> {
    scan(text).out
}

/// The numbers of `text`, and the words given as a field's value
/// (`interpolation: Step`) by the field's path.
fn scan(text: &str) -> NumberScan<'_> {
    let bytes = text.as_bytes();
    let mut scan = NumberScan {
        text,
        out: Vec::new(),
        words: BTreeMap::new(),
        items: Vec::new(),
        levels: Vec::new(),
        ident: None,
    };
    let mut i = 0;
    while i < bytes.len() {
        let c = bytes[i];
        match c {
            b'/' if bytes.get(i + 1) == Some(&b'/') => {
                i = ron_text::line_comment_end(bytes, i);
                continue;
            }
            b'/' if bytes.get(i + 1) == Some(&b'*') => {
                i = ron_text::block_comment_end(bytes, i);
                continue;
            }
            b'"' => {
                let end = ron_text::string_end(text, i).unwrap_or(bytes.len());
                scan.token(i, end);
                i = end;
                scan.ident = None;
                continue;
            }
            b'r' if matches!(bytes.get(i + 1), Some(b'"' | b'#')) => {
                let end = raw_string_end(bytes, i).min(bytes.len());
                scan.token(i, end);
                i = end;
                scan.ident = None;
                continue;
            }
            b'(' | b'[' => {
                scan.token(i, i + 1);
                scan.open(i);
            }
            b')' | b']' => {
                scan.word();
                scan.end_item();
                scan.levels.pop();
                scan.token(i, i + 1);
                scan.ident = None;
            }
            b',' => {
                scan.word();
                scan.end_item();
                scan.comma();
            }
            b':' => {
                if let Some(level) = scan.levels.last_mut() {
                    level.key = scan.ident.take();
                    level.value_start = None;
                }
            }
            b'-' | b'+' | b'.' | b'0'..=b'9' => {
                let end = scan.number(i);
                scan.token(i, end);
                i = end;
                continue;
            }
            c if c.is_ascii_alphabetic() || c == b'_' => {
                let start = i;
                while i < bytes.len() && (bytes[i].is_ascii_alphanumeric() || bytes[i] == b'_') {
                    i += 1;
                }
                scan.token(start, i);
                scan.ident = Some(text[start..i].to_string());
                continue;
            }
            _ => {}
        }
        i += 1;
    }
    scan
}

/// Just after a raw string `r"…"` or `r#"…"#` starting at `at` (the `r`),
/// taking the `#`s after `r` as its opening whatever follows them; past the
/// end of the text when it is not closed.
fn raw_string_end(bytes: &[u8], at: usize) -> usize {
    let hashes = bytes[at + 1..].iter().take_while(|&&b| b == b'#').count();
    let close: Vec<u8> = std::iter::once(b'"')
        .chain(std::iter::repeat_n(b'#', hashes))
        .collect();
    let mut i = at + 2 + hashes;
    while i < bytes.len() && !bytes[i..].starts_with(&close) {
        i += 1;
    }
    i + close.len()
}

/// What [`numbers`] has read so far: the numbers, the open brackets and the
/// identifier just read (a field name before `:`, or a variant before `(`).
struct NumberScan<'a> {
    text: &'a str,
    out: Vec<Number>,
    words: BTreeMap<String, String>,
    items: Vec<Item>,
    /// The outermost `Scene(` opens the root: its fields' paths start bare.
    levels: Vec<Level>,
    ident: Option<String>,
}

impl NumberScan<'_> {
    /// An opening bracket: a level whose path is the current item's, with the
    /// variant just named (`Torus(`) as one more segment.
    fn open(&mut self, at: usize) {
        let path = match self.levels.last() {
            None => String::new(),
            Some(level) => {
                let item = level.item();
                match self.ident.take() {
                    Some(variant) => join(&item, &variant),
                    None => item,
                }
            }
        };
        self.ident = None;
        self.levels.push(Level {
            path,
            at,
            index: 0,
            key: None,
            item_start: None,
            value_start: None,
            last_end: at + 1,
        });
    }

    /// A token from `start` to `end` in the innermost bracket.
    fn token(&mut self, start: usize, end: usize) {
        if let Some(level) = self.levels.last_mut() {
            level.item_start.get_or_insert(start);
            level.value_start.get_or_insert(start);
            level.last_end = end;
        }
    }

    /// The end of the current item (at its comma or its bracket's close).
    fn end_item(&mut self) {
        if let Some(level) = self.levels.last_mut()
            && let (Some(start), Some(value)) = (level.item_start.take(), level.value_start.take())
        {
            self.items.push(Item {
                path: level.item(),
                parent: level.path.clone(),
                span: start..level.last_end,
                value: value..level.last_end,
            });
        }
    }

    /// A field's value that is a bare word, at the end of its item.
    fn word(&mut self) {
        if let Some(level) = self.levels.last()
            && level.key.is_some()
            && let Some(word) = self.ident.take()
        {
            self.words.insert(level.item(), word);
        }
    }

    fn comma(&mut self) {
        if let Some(level) = self.levels.last_mut() {
            level.index += 1;
            level.key = None;
        }
        self.ident = None;
    }

    /// Reads the number literal starting at `start` (recorded when it is a
    /// finite number inside a bracket); where it ends.
    fn number(&mut self, start: usize) -> usize {
        let bytes = self.text.as_bytes();
        let mut end = start + 1;
        while end < bytes.len()
            && (bytes[end].is_ascii_alphanumeric()
                || bytes[end] == b'.'
                || bytes[end] == b'_'
                || (matches!(bytes[end], b'-' | b'+') && matches!(bytes[end - 1], b'e' | b'E')))
        {
            end += 1;
        }
        let literal = &self.text[start..end];
        let plain = literal.replace('_', "");
        if let (Some(level), Ok(value)) = (self.levels.last(), plain.parse::<f64>())
            && value.is_finite()
        {
            self.out.push(Number {
                path: level.item(),
                value,
                integer: !plain.contains(['.', 'e', 'E']),
                span: start..end,
                comment: comment_of(self.text, start, &self.levels),
            });
        }
        self.ident = None;
        end
    }
}

/// The `//` comment lines directly above the line of the number at `at`, or,
/// when there are none, above the line where its innermost enclosing bracket
/// that has some opens (the scene's outermost bracket excluded: its comments
/// are the file's), each line's text after `//`, joined by newlines; empty
/// when there are none.
fn comment_of(text: &str, at: usize, levels: &[Level]) -> String {
    std::iter::once(at)
        .chain(levels.iter().skip(1).rev().map(|l| l.at))
        .map(|at| comment_above(text, at))
        .find(|c| !c.is_empty())
        .unwrap_or_default()
}

/// The `//` comment lines directly above the line holding byte `at`.
fn comment_above(text: &str, at: usize) -> String {
    let line_start = text[..at].rfind('\n').map_or(0, |i| i + 1);
    let mut lines: Vec<&str> = text[..line_start]
        .lines()
        .rev()
        .map(str::trim)
        .take_while(|l| l.starts_with("//"))
        .map(|l| l.trim_start_matches('/').trim())
        .collect();
    lines.reverse();
    lines.join("\n")
}

/// `text` with the numbers at `values`' paths set to them (each written as the
/// literal it replaces was: an integer stays an integer). Paths that are not
/// in the text are named in the error.
pub fn with_values(text: &str, values: &BTreeMap<String, f64>) -> Result<String, String> {
    let found = numbers(text);
    let mut edits = Vec::new();
    for (path, value) in values {
        let n = found
            .iter()
            .find(|n| &n.path == path)
            .ok_or_else(|| format!("the scene has no number at `{path}`"))?;
        if !value.is_finite() {
            return Err(format!("`{path}`: {value} is not a number"));
        }
        edits.push((n.span.clone(), literal(*value, n.integer)));
    }
    edits.sort_by_key(|(span, _)| std::cmp::Reverse(span.start));
    let mut out = text.to_string();
    for (span, with) in edits {
        out.replace_range(span, &with);
    }
    Ok(out)
}

/// A value as RON reads it back to the same f64 (shortest round trip).
fn literal(value: f64, integer: bool) -> String {
    if integer {
        format!("{}", value.round() as i64)
    } else {
        format!("{value:?}")
    }
}

/// Which of a scene's top-level fields get sliders: the modelling ones, the
/// background and the march (its bounds, step, opacity and threshold). The
/// image's size and seeds are not looks; curves get handles instead.
const SLIDER_FIELDS: &[&str] = &[
    "march",
    "object",
    "modulation",
    "distortion",
    "camera",
    "lights",
    "shading",
    "background",
];

/// What the path of a 2D transfer function grid's value holds:
/// `….Grid.rows[j][i]`.
pub const GRID_ROWS: &str = ".Grid.rows[";

/// A slider for one number.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Param {
    /// Its path (what the page sends back).
    pub id: String,
    /// The top-level field it belongs to (the page groups by it).
    pub group: String,
    pub value: f64,
    pub min: f64,
    pub max: f64,
    pub step: f64,
    /// The scene's comment on it (the label's tooltip; empty: none).
    pub comment: String,
}

/// A control point's coordinate on a curve.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Coordinate {
    pub id: String,
    pub value: f64,
}

/// A control point: its x, and its y (a scalar curve) or its colour.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct ControlPoint {
    pub x: Coordinate,
    pub y: Option<Coordinate>,
    pub rgb: Option<[f64; 3]>,
}

/// A curve with draggable control points.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Curve {
    /// The path of its `points` list.
    pub id: String,
    pub points: Vec<ControlPoint>,
    /// `Linear`, `Spline` or `Step`.
    pub interpolation: String,
    /// The curve as the renderer evaluates it, at [`SAMPLES`] keys evenly
    /// from `from` to `to` (its domain: [0, 1] and every point): a scalar
    /// curve's values, or a colour map's colours (empty while its keys do
    /// not increase: the scene does not build).
    pub from: f64,
    pub to: f64,
    pub values: Vec<f64>,
    pub colours: Vec<[f64; 3]>,
}

/// How many keys a curve is sampled at for the page.
pub const SAMPLES: usize = 241;

/// The sliders and curves of a scene text. `ranges` keeps each slider's range
/// from one call to the next (a range is chosen around the value when its
/// path first appears, and again only if the value leaves it), so that a
/// moving slider's scale stays put.
pub fn controls(text: &str, ranges: &mut BTreeMap<String, (f64, f64)>) -> (Vec<Param>, Vec<Curve>) {
    let scanned = scan(text);
    let found = &scanned.out;
    let mut params = Vec::new();
    let mut curves: Vec<Curve> = Vec::new();
    for n in found {
        if let Some((curve, index, rest)) = curve_point(&n.path) {
            let at = match curves.iter().position(|c| c.id == curve) {
                Some(at) => at,
                None => {
                    curves.push(Curve {
                        id: curve.to_string(),
                        points: Vec::new(),
                        interpolation: String::new(),
                        from: 0.0,
                        to: 1.0,
                        values: Vec::new(),
                        colours: Vec::new(),
                    });
                    curves.len() - 1
                }
            };
            let points = &mut curves[at].points;
            if points.len() <= index {
                points.resize(
                    index + 1,
                    ControlPoint {
                        x: Coordinate {
                            id: String::new(),
                            value: 0.0,
                        },
                        y: None,
                        rgb: None,
                    },
                );
            }
            let point = &mut points[index];
            let coordinate = Coordinate {
                id: n.path.clone(),
                value: n.value,
            };
            match rest {
                "[0]" => point.x = coordinate,
                "[1]" => point.y = Some(coordinate),
                _ => {
                    if let Some(k) = ["[1][0]", "[1][1]", "[1][2]"]
                        .iter()
                        .position(|r| *r == rest)
                    {
                        point.rgb.get_or_insert([0.0; 3])[k] = n.value;
                    }
                }
            }
            continue;
        }
        let group = n.path.split(['.', '[']).next().unwrap_or_default();
        // A 2D transfer function's grid is painted with a brush, not slid.
        if !SLIDER_FIELDS.contains(&group) || n.path.contains(GRID_ROWS) {
            continue;
        }
        let (min, max) = match ranges.get(&n.path) {
            Some(&(lo, hi)) if lo <= n.value && n.value <= hi => (lo, hi),
            _ => range(&n.path, n.value, n.integer),
        };
        ranges.insert(n.path.clone(), (min, max));
        params.push(Param {
            id: n.path.clone(),
            group: group.to_string(),
            value: n.value,
            min,
            max,
            step: if n.integer { 1.0 } else { step(max - min) },
            comment: n.comment.clone(),
        });
    }
    ranges.retain(|path, _| params.iter().any(|p| &p.id == path));
    // A list of points is a curve when every point has an x and a y or colour.
    curves.retain(|c| {
        !c.points.is_empty()
            && c.points
                .iter()
                .all(|p| !p.x.id.is_empty() && (p.y.is_some() || p.rgb.is_some()))
    });
    for c in &mut curves {
        let owner = c.id.strip_suffix(".points").unwrap_or(&c.id);
        c.interpolation = scanned
            .words
            .get(&format!("{owner}.interpolation"))
            .cloned()
            .unwrap_or_else(|| "Linear".into());
        sample(c);
    }
    (params, curves)
}

/// Samples `c` with the renderer's own [`hypertexture::field::curve::Curve`].
fn sample(c: &mut Curve) {
    use hypertexture::desc::Interpolation;
    use hypertexture::field::curve::Curve as Evaluated;
    let xs: Vec<f32> = c.points.iter().map(|p| p.x.value as f32).collect();
    c.from = xs.iter().fold(0.0_f64, |lo, &x| lo.min(f64::from(x)));
    c.to = xs.iter().fold(1.0_f64, |hi, &x| hi.max(f64::from(x)));
    let interpolation = match c.interpolation.as_str() {
        "Linear" => Interpolation::Linear,
        "Spline" => Interpolation::Spline,
        "Step" => Interpolation::Step,
        _ => return,
    };
    if xs.windows(2).any(|w| w[1] <= w[0]) {
        return;
    }
    let keys = (0..SAMPLES).map(|i| {
        let t = i as f64 / (SAMPLES - 1) as f64;
        (c.from + t * (c.to - c.from)) as f32
    });
    if c.points.iter().all(|p| p.rgb.is_some()) {
        let map = Evaluated::new(
            interpolation,
            c.points
                .iter()
                .zip(&xs)
                .map(|(p, &x)| (x, p.rgb.unwrap_or_default().map(|v| v as f32))),
        );
        c.colours = keys.map(|t| map.eval(t).map(f64::from)).collect();
    } else {
        let map = Evaluated::new(
            interpolation,
            c.points.iter().zip(&xs).map(|(p, &x)| {
                let y = p.y.as_ref().map_or(0.0, |y| y.value);
                (x, [y as f32])
            }),
        );
        c.values = keys.map(|t| f64::from(map.eval1(t))).collect();
    }
}

/// A slider's step: the power of ten at most a thousandth of its span, so
/// that round values (0.4, not 0.39995) lie on its grid.
fn step(span: f64) -> f64 {
    if span > 0.0 {
        let exponent = (span / 1000.0).log10().floor() as i32;
        format!("1e{exponent}").parse().unwrap_or(1.0)
    } else {
        1.0
    }
}

/// `(curve path, point index, the rest)` when `path` is a coordinate of a
/// curve's control point: `….points[i][0]` (x), `[1]` (y) or `[1][k]` (colour).
fn curve_point(path: &str) -> Option<(&str, usize, &str)> {
    let at = path.rfind(".points[")?;
    let curve = &path[..at + ".points".len()];
    let rest = &path[at + ".points[".len()..];
    let close = rest.find(']')?;
    let index = rest[..close].parse().ok()?;
    let rest = &rest[close + 1..];
    matches!(rest, "[0]" | "[1]" | "[1][0]" | "[1][1]" | "[1][2]").then_some((curve, index, rest))
}

/// A sensible slider range for the number at `path`: the parameter's own
/// domain where the scene format fixes one, otherwise a span around the value.
fn range(path: &str, value: f64, integer: bool) -> (f64, f64) {
    let key = path
        .rsplit('.')
        .map(|s| s.split('[').next().unwrap_or(s))
        .find(|s| !s.is_empty())
        .unwrap_or_default();
    let component = path.ends_with(']');
    let fixed = match key {
        "bias" | "gain" => Some((0.01, 0.99)),
        "fov_y" => Some((5.0, 150.0)),
        "ambient" | "diffuse" | "specular" | "threshold" => Some((0.0, 1.0)),
        "colour" | "Colour" | "colours" if component => Some((0.0, 1.0)),
        "direction" | "up" => Some((-1.0, 1.0)),
        "shift" => Some((-1.0, 1.0)),
        "eye" | "look_at" | "position" => Some((value - 4.0, value + 4.0)),
        _ => None,
    };
    let (lo, hi) = fixed.unwrap_or(if integer {
        (1.0_f64.min(value), (2.0 * value).max(value + 4.0))
    } else if value > 0.0 {
        (0.0, 2.0 * value)
    } else if value < 0.0 {
        (2.0 * value, -2.0 * value)
    } else {
        (-1.0, 1.0)
    });
    (lo.min(value), hi.max(value))
}

#[cfg(test)]
mod tests {
    use super::*;

    const FUR: &str = include_str!("../../../scenes/fur.ron");

    #[test]
    fn curves_are_sampled_as_the_renderer_evaluates_them() {
        let text = include_str!("../../../scenes/gilet/isolines_r0.ron");
        let (_, curves) = controls(text, &mut BTreeMap::new());
        let alpha = curves.iter().find(|c| c.id == "alpha_map.points").unwrap();
        assert_eq!(alpha.interpolation, "Step");
        assert_eq!(
            (alpha.from, alpha.to, alpha.values.len()),
            (0.0, 1.0, SAMPLES)
        );
        let at = |t: f64| alpha.values[(t * (SAMPLES - 1) as f64).round() as usize];
        assert_eq!(
            (at(0.25), at(0.49), at(0.5), at(0.75)),
            (0.0, 0.0, 1.0, 1.0)
        );
        // A spline passes its points and bends between them.
        let spline =
            "Scene(m: (interpolation: Spline, points: [(0.0, 0.0), (0.5, 1.0), (1.0, 0.0)]))";
        let (_, curves) = controls(spline, &mut BTreeMap::new());
        let c = &curves[0];
        assert_eq!(c.interpolation, "Spline");
        let mid = c.values[(SAMPLES - 1) / 4];
        assert!(mid > 0.5, "above the straight segment: {mid}");
        // A colour map's colours; a linear one by default.
        let (_, curves) = controls(FUR, &mut BTreeMap::new());
        let colour = curves.iter().find(|c| c.id == "colour_map.points").unwrap();
        assert_eq!(colour.interpolation, "Linear");
        assert_eq!(colour.colours.len(), SAMPLES);
        assert!(colour.values.is_empty());
    }

    fn at<'a>(found: &'a [Number], path: &str) -> &'a Number {
        found
            .iter()
            .find(|n| n.path == path)
            .unwrap_or_else(|| panic!("no {path} in {:#?}", found))
    }

    #[test]
    fn numbers_are_named_by_their_fields_variants_and_positions() {
        let found = numbers(FUR);
        assert_eq!(at(&found, "object.Torus.minor_radius").value, 0.475);
        assert_eq!(at(&found, "camera.eye[1]").value, 2.3);
        assert_eq!(
            at(&found, "camera.projection.Perspective.fov_y").value,
            50.0
        );
        assert_eq!(at(&found, "modulation[0].Fur.frequency").value, 40.0);
        assert_eq!(at(&found, "march.step.Diagonal[0]").value, 200.0);
        assert!(at(&found, "march.step.Diagonal[0]").integer);
        assert_eq!(
            at(&found, "lights.sources[0].Directional.direction[2]").value,
            0.5
        );
        assert_eq!(at(&found, "colour_map.points[1][1][0]").value, 0.80);
        // The numbers in the comments are not the scene's.
        assert!(found.iter().all(|n| !n.path.is_empty()));
        assert_eq!(found.iter().filter(|n| n.value == 0.35).count(), 0);
        for n in &found {
            assert_eq!(FUR[n.span.clone()].parse::<f64>().unwrap(), n.value);
        }
    }

    #[test]
    fn a_value_written_back_changes_that_number_only() {
        let values: BTreeMap<String, f64> = [
            ("object.Torus.minor_radius".to_string(), 0.4),
            ("march.step.Diagonal[0]".to_string(), 120.4),
        ]
        .into();
        let text = with_values(FUR, &values).unwrap();
        let desc = hypertexture::scene::parse(&text, "fur.ron").unwrap();
        let before = hypertexture::scene::parse(FUR, "fur.ron").unwrap();
        assert_ne!(format!("{:?}", desc.object), format!("{:?}", before.object));
        assert!(text.contains("minor_radius: 0.4,"));
        assert!(text.contains("Diagonal(120)"));
        assert_eq!(
            numbers(&text).len(),
            numbers(FUR).len(),
            "the same numbers at the same paths"
        );
        let err = with_values(FUR, &[("object.Sphere.radius".to_string(), 1.0)].into());
        assert!(err.unwrap_err().contains("object.Sphere.radius"));
    }

    #[test]
    fn sliders_cover_the_modelling_fields_and_curves_get_handles() {
        let mut ranges = BTreeMap::new();
        let (params, curves) = controls(FUR, &mut ranges);
        let ids: Vec<&str> = params.iter().map(|p| p.id.as_str()).collect();
        for id in [
            "object.Torus.major_radius",
            "object.Torus.minor_radius",
            "object.Torus.softness",
            "modulation[0].Fur.frequency",
            "modulation[0].Fur.bias",
            "modulation[0].Fur.gain",
            "camera.eye[0]",
            "camera.projection.Perspective.fov_y",
            "lights.ambient[0]",
            "lights.sources[0].Directional.direction[0]",
            "lights.sources[0].Directional.colour[2]",
            "march.bounds.min[0]",
            "march.step.Diagonal[0]",
            "march.opacity",
            "march.threshold",
        ] {
            assert!(ids.contains(&id), "{id} in {ids:?}");
        }
        assert!(!ids.iter().any(|i| i.starts_with("image")));
        for p in &params {
            assert!(p.min <= p.value && p.value <= p.max, "{p:?}");
            assert!(p.step > 0.0);
        }
        let bias = params.iter().find(|p| p.id.ends_with("Fur.bias")).unwrap();
        assert_eq!((bias.min, bias.max, bias.step), (0.01, 0.99, 0.0001));
        assert_eq!(curves.len(), 1);
        assert_eq!(curves[0].id, "colour_map.points");
        assert_eq!(curves[0].points.len(), 3);
        assert_eq!(curves[0].points[1].x.value, 0.5);
        assert_eq!(curves[0].points[1].rgb, Some([0.80, 0.62, 0.42]));

        // A moved slider keeps its range.
        let moved =
            with_values(FUR, &[("object.Torus.softness".to_string(), 0.49)].into()).unwrap();
        let (again, _) = controls(&moved, &mut ranges);
        let s = |ps: &[Param]| {
            ps.iter()
                .find(|p| p.id == "object.Torus.softness")
                .map(|p| (p.min, p.max))
                .unwrap()
        };
        assert_eq!(s(&again), s(&params));
    }

    #[test]
    fn scalar_curves_and_transfer_functions_have_x_and_y() {
        let text = include_str!("../../../scenes/gilet/craters_r0.ron");
        let mut ranges = BTreeMap::new();
        let (params, curves) = controls(text, &mut ranges);
        let ids: Vec<&str> = curves.iter().map(|c| c.id.as_str()).collect();
        assert_eq!(
            ids,
            [
                "distortion.terms[0].transfer.Curve.points",
                "alpha_map.points",
                "colour_map.points"
            ]
        );
        let transfer = &curves[0];
        assert_eq!(transfer.points.len(), 6);
        assert_eq!(transfer.points[2].x.value, 0.74);
        assert_eq!(transfer.points[2].y.as_ref().unwrap().value, 1.0);
        assert!(
            params
                .iter()
                .any(|p| p.id == "distortion.terms[0].amplitude")
        );
        assert!(params.iter().any(|p| p.id == "shading.specular"));
        assert!(!params.iter().any(|p| p.id.contains("points")));
    }

    #[test]
    fn a_parameter_carries_the_comment_above_its_line_or_its_block() {
        let (params, _) = controls(FUR, &mut BTreeMap::new());
        let comment = |id: &str| {
            params
                .iter()
                .find(|p| p.id == id)
                .unwrap_or_else(|| panic!("no {id}"))
                .comment
                .clone()
        };
        let torus = "Inner (D = 1) radius r - s/2 = 0.35, outer (D = 0) radius r + s/2 = 0.60.";
        assert_eq!(comment("object.Torus.minor_radius"), torus);
        // No comment above the camera: the file's own, above `Scene(`, is not its.
        assert_eq!(comment("camera.eye[1]"), "");
        let text = "// the file\nScene(\n    lights: (\n        // warm key light\n        \
                    // from the left\n        sources: [Point(position: (1.0, 2.0, 3.0))],\n    ),\n\
                    \n    // a gap breaks it\n\n    march: (\n        opacity: 4.0,\n        \
                    /* a block comment is not a label's */\n        threshold: 0.9,\n    ),\n)";
        let (params, _) = controls(text, &mut BTreeMap::new());
        let comments: Vec<(&str, &str)> = params
            .iter()
            .map(|p| (p.id.as_str(), p.comment.as_str()))
            .collect();
        let light = "warm key light\nfrom the left";
        assert_eq!(
            comments,
            [
                ("lights.sources[0].Point.position[0]", light),
                ("lights.sources[0].Point.position[1]", light),
                ("lights.sources[0].Point.position[2]", light),
                ("march.opacity", ""),
                ("march.threshold", ""),
            ],
            "in file order"
        );
    }

    #[test]
    fn the_background_colour_is_three_sliders_in_zero_to_one() {
        let (params, _) = controls(FUR, &mut BTreeMap::new());
        let background: Vec<(&str, f64, f64, f64)> = params
            .iter()
            .filter(|p| p.group == "background")
            .map(|p| (p.id.as_str(), p.value, p.min, p.max))
            .collect();
        assert_eq!(
            background,
            [
                ("background.Colour[0]", 0.02, 0.0, 1.0),
                ("background.Colour[1]", 0.02, 0.0, 1.0),
                ("background.Colour[2]", 0.03, 0.0, 1.0),
            ]
        );
        let checker = "Scene(background: Checker(colours: ((0.9, 0.9, 0.85), (0.15, 0.15, 0.2)), squares: 10))";
        let (params, _) = controls(checker, &mut BTreeMap::new());
        let second = params
            .iter()
            .find(|p| p.id == "background.Checker.colours[1][2]")
            .expect("the checker's second colour");
        assert_eq!((second.value, second.min, second.max), (0.2, 0.0, 1.0));
        assert!(params.iter().any(|p| p.id == "background.Checker.squares"));
    }

    #[test]
    fn strings_comments_and_odd_text_do_not_confuse_the_scanner() {
        let text = "Scene(a: \"x: 1.0, (\", /* b: 2.0 /* nested */ 3.0 */ c: r#\"4\"#, d: [1e-3, -2, +.5])";
        let found = numbers(text);
        let paths: Vec<(&str, f64)> = found.iter().map(|n| (n.path.as_str(), n.value)).collect();
        assert_eq!(paths, [("d[0]", 1e-3), ("d[1]", -2.0), ("d[2]", 0.5)]);
        // Unbalanced or empty text: no panic.
        for t in [
            "",
            ")))",
            "(((",
            "Scene(x: 1.0",
            "[1, 2",
            "\"",
            "/*",
            "r#\"",
        ] {
            let _ = numbers(t);
            let _ = controls(t, &mut BTreeMap::new());
        }
    }
}
