//! The scene's shape as the studio edits it beyond its numbers: a control
//! point added to or deleted from a curve, and the word of a curve's
//! interpolation, of a distortion term's operator and `enabled` switch and
//! of a distortion's vector field set; and what the page shows of each
//! distortion and each 2D shape transfer function grid.
//!
//! Each edit rewrites only the bytes it concerns (a point and the separator
//! before or after it, a field's value, or a field added beside the others)
//! and follows the list's own layout (one line, or one item a line), so the
//! text stays the author's and the scene parser still decides whether it is
//! a scene. A grid's values are numbers: the page paints them as parameters
//! ([`params::with_values`]).

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::service::params::{self, GRID_ROWS, Item, Scanned};

/// A structural edit as the page sends it: `{"op": "add_point", …}`.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(tag = "op", rename_all = "snake_case", deny_unknown_fields)]
pub enum ShapeEdit {
    /// A control point at key `x` added, in key order, to the curve whose
    /// `points` list is at `curve` (`alpha_map.points`): with the value `y`
    /// on a scalar curve, the linear colour `rgb` on a colour map.
    AddPoint {
        curve: String,
        x: f64,
        #[serde(default)]
        y: Option<f64>,
        #[serde(default)]
        rgb: Option<[f64; 3]>,
    },
    /// Control point `index` of the curve at `curve` deleted (a curve keeps
    /// at least one).
    DeletePoint { curve: String, index: usize },
    /// The field at `path` set to the word `to`: a curve's `interpolation`
    /// (`Linear`, `Spline`, `Step`), a term's `operator` (`Sum`, `Blend`) or
    /// `enabled` (`true`, `false`), a distortion's `field` (`Boundary`,
    /// `Radial`, `Constant`, `Curl`, `Perturbed`: a new variant with
    /// default parameters). A field the text leaves to its default is added.
    Set { path: String, to: String },
}

/// The fields [`ShapeEdit::Set`] sets: the field's name, a sibling field
/// that shows its bracket is the right kind (a curve has `points`, a term a
/// `transfer`, a distortion `terms`), and the words it takes.
const WORDS: &[(&str, &str, &[&str])] = &[
    ("interpolation", "points", &["Linear", "Spline", "Step"]),
    ("operator", "transfer", &["Sum", "Blend"]),
    ("enabled", "transfer", &["true", "false"]),
    (
        "field",
        "terms",
        &["Boundary", "Radial", "Constant", "Curl", "Perturbed"],
    ),
];

/// A vector field's variant as a new field is written: its parameters at
/// values that build on a sphere, box or torus.
fn field_literal(variant: &str) -> String {
    match variant {
        "Radial" => "Radial(centre: (0.0, 0.0, 0.0))".into(),
        "Constant" => "Constant(0.0, 1.0, 0.0)".into(),
        "Curl" => "Curl(axis: (0.0, 1.0, 0.0), twist: 2.0)".into(),
        "Perturbed" => "Perturbed(field: Boundary, amplitude: 0.3, frequency: 6.0)".into(),
        other => other.into(),
    }
}

/// `text` with `edits` made one after another (each on the text the one
/// before it gave).
pub fn apply(text: &str, edits: &[ShapeEdit]) -> Result<String, String> {
    let mut text = text.to_string();
    for edit in edits {
        let scanned = params::scanned(&text);
        text = match edit {
            ShapeEdit::AddPoint { curve, x, y, rgb } => {
                add_point(&text, &scanned, curve, *x, (*y, *rgb))?
            }
            ShapeEdit::DeletePoint { curve, index } => {
                delete_point(&text, &scanned, curve, *index)?
            }
            ShapeEdit::Set { path, to } => set_word(&text, &scanned, path, to)?,
        };
    }
    Ok(text)
}

/// The items of the bracket at `parent`, in the order they stand.
fn children<'a>(scanned: &'a Scanned, parent: &str) -> Vec<&'a Item> {
    scanned
        .items
        .iter()
        .filter(|i| i.parent == parent)
        .collect()
}

fn number(scanned: &Scanned, path: &str) -> Option<f64> {
    scanned
        .numbers
        .iter()
        .find(|n| n.path == path)
        .map(|n| n.value)
}

/// What goes between two items of `items`' bracket: a comma and the white
/// space before the second item of the bracket's first pair (its line break
/// and indent), or `", "`.
fn separator(text: &str, items: &[&Item]) -> String {
    let Some(pair) = items.windows(2).next() else {
        return ", ".into();
    };
    let between = &text[pair[0].span.end..pair[1].span.start];
    let space = &between[between.trim_end().len()..];
    if space.is_empty() {
        ", ".into()
    } else {
        format!(",{space}")
    }
}

/// The control points of the curve whose `points` list is at `curve`.
fn points<'a>(scanned: &'a Scanned, curve: &str) -> Result<Vec<&'a Item>, String> {
    let items = children(scanned, curve);
    if !curve.ends_with(".points") || items.is_empty() {
        return Err(format!("the scene has no curve at `{curve}`"));
    }
    Ok(items)
}

fn add_point(
    text: &str,
    scanned: &Scanned,
    curve: &str,
    x: f64,
    (y, rgb): (Option<f64>, Option<[f64; 3]>),
) -> Result<String, String> {
    let items = points(scanned, curve)?;
    let keys = (0..items.len())
        .map(|k| number(scanned, &format!("{curve}[{k}][0]")))
        .collect::<Option<Vec<f64>>>()
        .ok_or_else(|| format!("`{curve}`: a point without a number for its key"))?;
    if !(x.is_finite() && (0.0..=1.0).contains(&x)) {
        return Err(format!("`{curve}`: a key lies in [0, 1], not {x}"));
    }
    if keys.contains(&x) {
        return Err(format!("`{curve}` has a point at {x} already"));
    }
    let colour = number(scanned, &format!("{curve}[0][1][0]")).is_some();
    let literal = match (y, rgb, colour) {
        (Some(y), None, false) if y.is_finite() => format!("({x:?}, {y:?})"),
        (None, Some(c), true) if c.iter().all(|v| v.is_finite() && *v >= 0.0) => {
            format!("({x:?}, ({:?}, {:?}, {:?}))", c[0], c[1], c[2])
        }
        (_, _, false) => {
            return Err(format!(
                "`{curve}` is a scalar curve: a new point needs a finite `y` (and no `rgb`)"
            ));
        }
        (_, _, true) => {
            return Err(format!(
                "`{curve}` is a colour map: a new point needs `rgb`, three finite numbers ≥ 0 \
                 (and no `y`)"
            ));
        }
    };
    let at = keys.iter().filter(|&&k| k < x).count();
    let sep = separator(text, &items);
    let mut out = text.to_string();
    if at == 0 {
        out.insert_str(items[0].span.start, &format!("{literal}{sep}"));
    } else {
        out.insert_str(items[at - 1].span.end, &format!("{sep}{literal}"));
    }
    Ok(out)
}

fn delete_point(
    text: &str,
    scanned: &Scanned,
    curve: &str,
    index: usize,
) -> Result<String, String> {
    let items = points(scanned, curve)?;
    let n = items.len();
    if index >= n {
        return Err(format!(
            "`{curve}` has {n} points: there is no point {index}"
        ));
    }
    if n == 1 {
        return Err(format!(
            "`{curve}` has one point left: a curve needs at least one"
        ));
    }
    let cut = if index + 1 < n {
        items[index].span.start..items[index + 1].span.start
    } else {
        items[index - 1].span.end..items[index].span.end
    };
    let mut out = text.to_string();
    out.replace_range(cut, "");
    Ok(out)
}

/// The identifier a value starts with (`Radial` of `Radial(centre: …)`).
fn leading_word(value: &str) -> &str {
    let end = value
        .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
        .unwrap_or(value.len());
    &value[..end]
}

fn set_word(text: &str, scanned: &Scanned, path: &str, to: &str) -> Result<String, String> {
    let (parent, name) = path
        .rsplit_once('.')
        .ok_or_else(|| format!("`{path}` names no field of a bracket"))?;
    let (_, sibling, words) = WORDS.iter().find(|(n, _, _)| *n == name).ok_or_else(|| {
        let names: Vec<&str> = WORDS.iter().map(|w| w.0).collect();
        format!("`{path}`: the studio sets the fields {names:?} only")
    })?;
    if !words.contains(&to) {
        return Err(format!("`{path}`: `{to}` is not one of {words:?}"));
    }
    let items = children(scanned, parent);
    if !items
        .iter()
        .any(|i| i.path == format!("{parent}.{sibling}"))
    {
        return Err(format!(
            "the scene has no `{parent}` with a `{sibling}` field to set `{name}` in"
        ));
    }
    let literal = if name == "field" {
        field_literal(to)
    } else {
        to.to_string()
    };
    let mut out = text.to_string();
    match items.iter().find(|i| i.path == path) {
        // The same variant keeps its parameters.
        Some(item) if leading_word(&text[item.value.clone()]) == to => {}
        Some(item) => out.replace_range(item.value.clone(), &literal),
        None => {
            let sep = separator(text, &items);
            if matches!(name, "interpolation" | "field") {
                out.insert_str(items[0].span.start, &format!("{name}: {literal}{sep}"));
            } else if let Some(last) = items.last() {
                out.insert_str(last.span.end, &format!("{sep}{name}: {literal}"));
            }
        }
    }
    Ok(out)
}

/// A distortion as the page shows it: its vector field and its terms.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct DistortionView {
    /// The path of its bracket (`distortion`, `object.Hypertexture.distortion`).
    pub id: String,
    /// The vector field's variant (`Boundary` when the text leaves it out).
    pub field: String,
    pub terms: Vec<TermView>,
}

/// A noise term of a distortion.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct TermView {
    /// The path of its bracket (`distortion.terms[0]`).
    pub id: String,
    /// `Sum` or `Blend`.
    pub operator: String,
    pub enabled: bool,
    /// Its shape transfer function's kind: `Curve` or `Grid`.
    pub transfer: String,
}

/// A 2D shape transfer function's grid, painted with a brush.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct GridView {
    /// The path of its `rows` (a value's path is `ID[j][i]`).
    pub id: String,
    pub rows: usize,
    pub columns: usize,
    /// Row-major: row j (object density j / (rows − 1)), column i (noise).
    pub values: Vec<f64>,
}

/// The distortions and grids of `text`.
pub fn looks(text: &str) -> (Vec<DistortionView>, Vec<GridView>) {
    let scanned = params::scanned(text);
    (distortions(text, &scanned), grids(&scanned))
}

fn distortions(text: &str, scanned: &Scanned) -> Vec<DistortionView> {
    let word = |path: &str| scanned.words.get(path).map(String::as_str);
    let mut out = Vec::new();
    for item in &scanned.items {
        if item.path.rsplit('.').next() != Some("distortion") {
            continue;
        }
        let value = &text[item.value.clone()];
        let id = match value.as_bytes().first() {
            Some(b'(') => item.path.clone(),
            _ if value.starts_with("Some(") => format!("{}.Some", item.path),
            _ => continue,
        };
        let children = children(scanned, &id);
        let terms_path = format!("{id}.terms");
        if !children.iter().any(|c| c.path == terms_path) {
            continue;
        }
        let field = children
            .iter()
            .find(|c| c.path == format!("{id}.field"))
            .map_or("Boundary", |c| leading_word(&text[c.value.clone()]));
        let terms = self::children(scanned, &terms_path)
            .into_iter()
            .map(|t| TermView {
                id: t.path.clone(),
                operator: word(&format!("{}.operator", t.path))
                    .unwrap_or("Sum")
                    .to_string(),
                enabled: word(&format!("{}.enabled", t.path)) != Some("false"),
                transfer: scanned
                    .items
                    .iter()
                    .find(|i| i.path == format!("{}.transfer", t.path))
                    .map_or("", |i| leading_word(&text[i.value.clone()]))
                    .to_string(),
            })
            .collect();
        out.push(DistortionView {
            id,
            field: field.to_string(),
            terms,
        });
    }
    out
}

fn grids(scanned: &Scanned) -> Vec<GridView> {
    let mut cells: BTreeMap<String, Vec<(usize, usize, f64)>> = BTreeMap::new();
    for n in &scanned.numbers {
        let Some(at) = n.path.find(GRID_ROWS) else {
            continue;
        };
        let id = &n.path[..at + GRID_ROWS.len() - 1];
        let rest = &n.path[at + GRID_ROWS.len()..];
        let parsed = rest
            .strip_suffix(']')
            .and_then(|r| r.split_once("]["))
            .and_then(|(j, i)| Some((j.parse().ok()?, i.parse().ok()?)));
        if let Some((j, i)) = parsed {
            cells
                .entry(id.to_string())
                .or_default()
                .push((j, i, n.value));
        }
    }
    let mut out: Vec<GridView> = cells
        .into_iter()
        .map(|(id, cells)| {
            let rows = cells.iter().map(|c| c.0 + 1).max().unwrap_or(0);
            let columns = cells.iter().map(|c| c.1 + 1).max().unwrap_or(0);
            let mut values = vec![0.0; rows * columns];
            for (j, i, v) in cells {
                values[j * columns + i] = v;
            }
            GridView {
                id,
                rows,
                columns,
                values,
            }
        })
        .collect();
    // In the order they stand in the text.
    let first = |id: &str| {
        scanned
            .numbers
            .iter()
            .position(|n| n.path.starts_with(id))
            .unwrap_or(usize::MAX)
    };
    out.sort_by_key(|g| first(&g.id));
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    const CRATERS: &str = include_str!("../../../../scenes/gilet/craters_r0.ron");
    const BUMPS: &str = include_str!("../../../../scenes/gilet/multi_blend_bumps.ron");
    const MUSHROOMS: &str = include_str!("../../../../scenes/gilet/mushrooms.ron");
    const FUR: &str = include_str!("../../../../scenes/fur.ron");

    fn parses(text: &str) -> hypertexture::desc::SceneDesc {
        hypertexture::scene::parse(text, "edited.ron").unwrap_or_else(|e| panic!("{e}\n{text}"))
    }

    fn set(path: &str, to: &str) -> ShapeEdit {
        ShapeEdit::Set {
            path: path.into(),
            to: to.into(),
        }
    }

    const ALPHA: &str = "alpha_map.points";

    #[test]
    fn a_point_is_added_in_key_order_and_deleted_with_its_separator() {
        let add = |x, y| ShapeEdit::AddPoint {
            curve: ALPHA.into(),
            x,
            y: Some(y),
            rgb: None,
        };
        let text = apply(CRATERS, &[add(0.25, 0.5)]).unwrap();
        assert!(
            text.contains(
                "alpha_map: (interpolation: Step, points: [(0.0, 0.0), (0.25, 0.5), (0.5, 1.0)]),"
            ),
            "{text}"
        );
        assert_eq!(text.len(), CRATERS.len() + "(0.25, 0.5), ".len());
        let desc = parses(&text);
        assert_eq!(desc.alpha_map.unwrap().points.len(), 3);
        // First and last.
        let ends = apply(CRATERS, &[add(0.75, 1.0)]).unwrap();
        assert!(ends.contains("[(0.0, 0.0), (0.5, 1.0), (0.75, 1.0)]"));
        let delete = |index| ShapeEdit::DeletePoint {
            curve: ALPHA.into(),
            index,
        };
        // Deleting the points added gives the text back byte for byte.
        assert_eq!(apply(&text, &[delete(1)]).unwrap(), CRATERS);
        assert_eq!(apply(&ends, &[delete(2)]).unwrap(), CRATERS);
        let first = apply(CRATERS, &[delete(0)]).unwrap();
        assert!(first.contains("alpha_map: (interpolation: Step, points: [(0.5, 1.0)]),"));
        parses(&first);
        // The last point stays; a point at a key taken, out of [0, 1] or of
        // the wrong kind is refused, naming the curve.
        for (edits, says) in [
            (vec![delete(0), delete(0)], "one point left"),
            (vec![delete(2)], "no point 2"),
            (vec![add(0.5, 0.0)], "a point at 0.5 already"),
            (vec![add(1.5, 0.0)], "not 1.5"),
            (
                vec![ShapeEdit::AddPoint {
                    curve: ALPHA.into(),
                    x: 0.3,
                    y: None,
                    rgb: Some([1.0, 0.0, 0.0]),
                }],
                "scalar curve",
            ),
            (
                vec![ShapeEdit::DeletePoint {
                    curve: "camera.eye".into(),
                    index: 0,
                }],
                "no curve at `camera.eye`",
            ),
        ] {
            let err = apply(CRATERS, &edits).unwrap_err();
            assert!(err.contains(says), "{err}");
        }
    }

    #[test]
    fn a_colour_stop_is_added_to_a_multi_line_map_in_its_layout() {
        let add = ShapeEdit::AddPoint {
            curve: "colour_map.points".into(),
            x: 0.25,
            y: None,
            rgb: Some([0.5, 0.25, 0.125]),
        };
        let one_line = "points: [(0.0, (0.55, 0.38, 0.22)), (0.5, (0.80, 0.62, 0.42)), (1.0, (0.95, 0.85, 0.70))]";
        assert!(FUR.contains(one_line));
        let fur = FUR.replace(
            one_line,
            "points: [\n            (0.0, (0.55, 0.38, 0.22)),\n            (0.5, (0.80, 0.62, 0.42)),\n            (1.0, (0.95, 0.85, 0.70)),\n        ]",
        );
        let text = apply(&fur, &[add]).unwrap();
        let desc = parses(&text);
        assert_eq!(desc.colour_map.points.len(), 4);
        assert_eq!(desc.colour_map.points[1].0, 0.25);
        assert_eq!(desc.colour_map.points[1].1.0, [0.5, 0.25, 0.125]);
        // On its own line, indented as the others.
        let (before, after) = text.split_once("(0.25, (0.5, 0.25, 0.125))").unwrap();
        assert!(
            before.ends_with("(0.0, (0.55, 0.38, 0.22)),\n            "),
            "{before}"
        );
        assert!(after.starts_with(",\n            (0.5,"), "{after:.40}");
        let back = ShapeEdit::DeletePoint {
            curve: "colour_map.points".into(),
            index: 1,
        };
        assert_eq!(apply(&text, &[back]).unwrap(), fur);
        // On one line, between its neighbours.
        let add = ShapeEdit::AddPoint {
            curve: "colour_map.points".into(),
            x: 0.75,
            y: None,
            rgb: Some([1.0, 0.5, 0.0]),
        };
        let text = apply(FUR, &[add]).unwrap();
        assert!(text.contains("(0.5, (0.80, 0.62, 0.42)), (0.75, (1.0, 0.5, 0.0)), (1.0,"));
    }

    #[test]
    fn words_are_set_in_place_or_added_beside_the_fields() {
        // An interpolation written: replaced; one left out: added first.
        let text = apply(CRATERS, &[set("alpha_map.interpolation", "Linear")]).unwrap();
        assert_eq!(
            text,
            CRATERS.replace(
                "alpha_map: (interpolation: Step,",
                "alpha_map: (interpolation: Linear,"
            )
        );
        let transfer = "distortion.terms[0].transfer.Curve.interpolation";
        let text = apply(BUMPS, &[set(transfer, "Step")]).unwrap();
        assert!(text.contains(
            "transfer: Curve(interpolation: Step, points: [(0.0, 1.0), (0.5, 0.0), (1.0, 1.0)]), operator: Sum),\n            (amplitude: 0.025"
        ));
        parses(&text);
        let text = apply(CRATERS, &[set("colour_map.interpolation", "Step")]).unwrap();
        assert!(
            text.contains("colour_map: (interpolation: Step, points: [(0.0, (0.7, 0.74, 0.8))]),")
        );
        // A term's operator written; its enabled switch added last, in the
        // term's layout (one field a line).
        let text = apply(BUMPS, &[set("distortion.terms[4].operator", "Sum")]).unwrap();
        assert_eq!(text.matches("operator: Blend").count(), 0);
        let text = apply(CRATERS, &[set("distortion.terms[0].enabled", "false")]).unwrap();
        assert!(
            text.contains("(1.0, 0.3)]),\n            enabled: false,\n        )]"),
            "{text}"
        );
        let desc = parses(&text);
        assert!(!desc.distortion.unwrap().terms[0].enabled);
        let on = apply(&text, &[set("distortion.terms[0].enabled", "true")]).unwrap();
        assert!(on.contains("enabled: true"));
        // A field's variant with its default parameters; the same variant
        // keeps its own.
        for (to, literal) in [
            ("Radial", "field: Radial(centre: (0.0, 0.0, 0.0)),"),
            ("Constant", "field: Constant(0.0, 1.0, 0.0),"),
            ("Curl", "field: Curl(axis: (0.0, 1.0, 0.0), twist: 2.0),"),
            (
                "Perturbed",
                "field: Perturbed(field: Boundary, amplitude: 0.3, frequency: 6.0),",
            ),
        ] {
            let text = apply(CRATERS, &[set("distortion.field", to)]).unwrap();
            assert!(text.contains(literal), "{to}");
            parses(&text);
            assert_eq!(apply(&text, &[set("distortion.field", to)]).unwrap(), text);
        }
    }

    #[test]
    fn a_bad_word_or_path_is_refused_with_the_reason() {
        for (path, to, says) in [
            ("alpha_map.interpolation", "Cubic", "`Cubic` is not one of"),
            ("distortion.terms[0].operator", "Max", "not one of"),
            (
                "camera.interpolation",
                "Step",
                "no `camera` with a `points` field",
            ),
            (
                "distortion.terms[3].enabled",
                "false",
                "no `distortion.terms[3]`",
            ),
            ("object.Sphere.radius", "Step", "sets the fields"),
            ("interpolation", "Step", "names no field"),
        ] {
            let err = apply(CRATERS, &[set(path, to)]).unwrap_err();
            assert!(err.contains(says), "{path}: {err}");
        }
        // A message the page could send by mistake: a clear error from serde.
        let bad: Result<ShapeEdit, _> =
            serde_json::from_str(r#"{"op": "add_point", "curve": "alpha_map.points"}"#);
        assert!(bad.unwrap_err().to_string().contains("missing field `x`"));
        let bad: Result<ShapeEdit, _> = serde_json::from_str(r#"{"op": "explode"}"#);
        assert!(
            bad.unwrap_err()
                .to_string()
                .contains("unknown variant `explode`")
        );
    }

    #[test]
    fn distortions_and_grids_are_shown_as_the_text_has_them() {
        let (distortions, grids) = looks(BUMPS);
        assert!(grids.is_empty());
        assert_eq!(distortions.len(), 1);
        let d = &distortions[0];
        assert_eq!(
            (d.id.as_str(), d.field.as_str()),
            ("distortion", "Boundary")
        );
        let terms: Vec<(&str, &str, bool)> = d
            .terms
            .iter()
            .map(|t| (t.id.as_str(), t.operator.as_str(), t.enabled))
            .collect();
        assert_eq!(terms.len(), 5);
        assert_eq!(terms[0], ("distortion.terms[0]", "Sum", true));
        assert_eq!(terms[4], ("distortion.terms[4]", "Blend", true));
        let off = apply(CRATERS, &[set("distortion.terms[0].enabled", "false")]).unwrap();
        let (d, _) = looks(&off);
        assert!(!d[0].terms[0].enabled);
        assert_eq!(d[0].terms[0].operator, "Sum", "the default");

        let (d, grids) = looks(MUSHROOMS);
        assert_eq!(d[0].terms[0].transfer, "Grid");
        assert_eq!(grids.len(), 1);
        let g = &grids[0];
        assert_eq!(g.id, "distortion.terms[0].transfer.Grid.rows");
        assert_eq!((g.rows, g.columns), (9, 9));
        assert_eq!(g.values[4], 0.3);
        assert_eq!(g.values[2 * 9 + 6], 0.8);
        // A cell painted is a number written; grid values are no sliders.
        let painted =
            params::with_values(MUSHROOMS, &[(format!("{}[2][6]", g.id), 0.25)].into()).unwrap();
        assert!(painted.contains("[0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.25, 1.0, 1.0],"));
        parses(&painted);
        let (params, _) = params::controls(MUSHROOMS, &mut BTreeMap::new());
        assert!(params.iter().all(|p| !p.id.contains("Grid")));
        assert!(
            params
                .iter()
                .any(|p| p.id == "distortion.terms[0].amplitude")
        );
    }
}
