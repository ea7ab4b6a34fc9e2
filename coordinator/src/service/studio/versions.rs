//! One state owned by the server, for every tab: the scene text and knob
//! values carry a *version*, one more per edit that changes them. A tab's
//! edit names the version it was made on; when another tab edited since, the
//! edit is merged onto the current version if it touches other values (other
//! knobs, other numbers of the text, other lines), and refused as a conflict
//! when it touches the same one. A stale tab never silently undoes another.

use std::collections::{BTreeMap, VecDeque};

use crate::service::params;

/// How many versions are kept to merge stale edits against.
pub const KEPT: usize = 256;

/// One version of the live state.
#[derive(Clone, Debug, PartialEq)]
pub struct Version {
    pub number: u64,
    /// The text as the page shows it (knob values written as defaults).
    pub shown: String,
    pub knobs: BTreeMap<String, f64>,
}

/// The versions kept, oldest first; the last is the current one.
#[derive(Debug)]
pub struct Versions {
    kept: VecDeque<Version>,
}

/// An edit as a tab makes it: a new text, or knob and number values.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Edit {
    pub text: Option<String>,
    pub knobs: BTreeMap<String, f64>,
    pub params: BTreeMap<String, f64>,
}

/// Why a stale edit is refused.
#[derive(Debug, PartialEq)]
pub enum Stale {
    /// It changes a value another tab changed since, to another value.
    Conflict(String),
    /// Its version is unknown: newer than the current, or no longer kept.
    Unknown(String),
}

impl Versions {
    /// Version 0: the text as opened, no knob values yet.
    pub fn new(shown: &str) -> Versions {
        Versions {
            kept: VecDeque::from([Version {
                number: 0,
                shown: shown.to_string(),
                knobs: BTreeMap::new(),
            }]),
        }
    }

    pub fn current(&self) -> &Version {
        self.kept.back().expect("a version is always kept")
    }

    /// Records the state after an edit: a new version when the text or the
    /// knob values changed. Returns whether it did.
    pub fn record(&mut self, shown: &str, knobs: &BTreeMap<String, f64>) -> bool {
        let now = self.current();
        if now.shown == shown && now.knobs == *knobs {
            return false;
        }
        let number = now.number + 1;
        self.kept.push_back(Version {
            number,
            shown: shown.to_string(),
            knobs: knobs.clone(),
        });
        while self.kept.len() > KEPT {
            self.kept.pop_front();
        }
        true
    }

    /// `edit`, made on version `base` (none: on the current one), as an edit
    /// of the current version.
    pub fn rebase(&self, base: Option<u64>, edit: Edit) -> Result<Edit, Stale> {
        let now = self.current();
        let Some(base) = base.filter(|&b| b != now.number) else {
            return Ok(edit);
        };
        if base > now.number {
            return Err(Stale::Unknown(format!(
                "version {base} is not known: the studio is at version {}",
                now.number
            )));
        }
        let then = self.kept.iter().find(|v| v.number == base).ok_or_else(|| {
            Stale::Unknown(format!(
                "the edit was made on version {base}, which the studio no longer keeps \
                     (it is at version {}): the page shows the current state",
                now.number
            ))
        })?;
        match edit.text {
            Some(ours) => merge_text(then, now, ours),
            None => Ok(Edit {
                text: None,
                knobs: merge_values("knob", &then.knobs, &now.knobs, &now.knobs, edit.knobs)?,
                params: merge_values(
                    "number",
                    &numbers(&then.shown),
                    &numbers(&now.shown),
                    &BTreeMap::new(),
                    edit.params,
                )?,
            }),
        }
    }
}

/// A text edited from `then` merged line by line with the edits made since
/// (`now`): refused where both changed the same lines.
fn merge_text(then: &Version, now: &Version, ours: String) -> Result<Edit, Stale> {
    if ours == then.shown {
        // Nothing of the text changed in this tab: the current state stands.
        return Ok(Edit {
            text: None,
            knobs: now.knobs.clone(),
            params: BTreeMap::new(),
        });
    }
    match diffy::merge(&then.shown, &ours, &now.shown) {
        Ok(merged) => Ok(Edit {
            text: Some(merged),
            ..Edit::default()
        }),
        Err(_) => Err(Stale::Conflict(format!(
            "another tab changed the same lines of the text since version {} (the studio is at \
             version {}): take the current text, or send yours over it",
            then.number, now.number
        ))),
    }
}

/// The values of `ours` that differ from `then` (those this tab changed),
/// checked against the changes since (`then` → `now`), laid over `start`.
fn merge_values(
    what: &str,
    then: &BTreeMap<String, f64>,
    now: &BTreeMap<String, f64>,
    start: &BTreeMap<String, f64>,
    ours: BTreeMap<String, f64>,
) -> Result<BTreeMap<String, f64>, Stale> {
    let mut merged = start.clone();
    for (name, value) in ours {
        let before = then.get(&name);
        if before == Some(&value) {
            continue;
        }
        let current = now.get(&name);
        if current != before && current != Some(&value) {
            return Err(Stale::Conflict(format!(
                "another tab set {what} `{name}` to {} since (yours: {value}): the page shows its \
                 value",
                current.map_or_else(|| "nothing".to_string(), f64::to_string)
            )));
        }
        merged.insert(name, value);
    }
    Ok(merged)
}

/// The numbers of a text by path.
fn numbers(text: &str) -> BTreeMap<String, f64> {
    params::numbers(text)
        .into_iter()
        .map(|n| (n.path, n.value))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const TEXT: &str = "Scene(\n    // a comment\n    a: 1.0,\n    b: 2.0,\n)\n";

    fn knobs(pairs: &[(&str, f64)]) -> BTreeMap<String, f64> {
        pairs.iter().map(|(k, v)| (k.to_string(), *v)).collect()
    }

    fn versions() -> Versions {
        let mut v = Versions::new(TEXT);
        assert!(v.record(TEXT, &knobs(&[("bias", 0.3), ("gain", 0.9)])));
        v
    }

    #[test]
    fn an_edit_on_the_current_version_is_taken_as_it_is() {
        let v = versions();
        let edit = Edit {
            knobs: knobs(&[("bias", 0.5)]),
            ..Edit::default()
        };
        assert_eq!(v.rebase(Some(1), edit.clone()), Ok(edit.clone()));
        assert_eq!(v.rebase(None, edit.clone()), Ok(edit));
        let mut v = v;
        assert!(
            !v.record(TEXT, &knobs(&[("bias", 0.3), ("gain", 0.9)])),
            "no change, no version"
        );
    }

    #[test]
    fn a_stale_knob_edit_keeps_the_other_tabs_values() {
        let mut v = versions();
        v.record(TEXT, &knobs(&[("bias", 0.67), ("gain", 0.9)]));
        // Made on version 1: gain moved, bias as it was then.
        let edit = Edit {
            knobs: knobs(&[("bias", 0.3), ("gain", 0.5)]),
            ..Edit::default()
        };
        let merged = v.rebase(Some(1), edit).unwrap();
        assert_eq!(merged.knobs, knobs(&[("bias", 0.67), ("gain", 0.5)]));
        // The same knob to another value: a conflict naming it.
        let edit = Edit {
            knobs: knobs(&[("bias", 0.1), ("gain", 0.9)]),
            ..Edit::default()
        };
        match v.rebase(Some(1), edit) {
            Err(Stale::Conflict(why)) => assert!(why.contains("`bias` to 0.67"), "{why}"),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_stale_number_edit_touches_only_its_own_numbers() {
        let mut v = versions();
        let b_moved = TEXT.replace("b: 2.0", "b: 3.0");
        v.record(&b_moved, &knobs(&[("bias", 0.3), ("gain", 0.9)]));
        let edit = Edit {
            params: knobs(&[("a", 1.5), ("b", 2.0)]),
            ..Edit::default()
        };
        let merged = v.rebase(Some(1), edit).unwrap();
        assert_eq!(merged.params, knobs(&[("a", 1.5)]), "b is the other tab's");
        let edit = Edit {
            params: knobs(&[("b", 2.5)]),
            ..Edit::default()
        };
        assert!(matches!(v.rebase(Some(1), edit), Err(Stale::Conflict(_))));
    }

    #[test]
    fn a_stale_text_edit_is_merged_line_by_line() {
        let mut v = versions();
        let theirs = TEXT.replace("b: 2.0", "b: 3.0");
        v.record(&theirs, &knobs(&[("bias", 0.3), ("gain", 0.9)]));
        let ours = TEXT.replace("// a comment", "// my comment");
        let merged = v
            .rebase(
                Some(1),
                Edit {
                    text: Some(ours),
                    ..Edit::default()
                },
            )
            .unwrap();
        assert_eq!(
            merged.text.as_deref(),
            Some("Scene(\n    // my comment\n    a: 1.0,\n    b: 3.0,\n)\n")
        );
        // Their line changed too: a conflict.
        let ours = TEXT.replace("b: 2.0", "b: 4.0");
        let edit = Edit {
            text: Some(ours),
            ..Edit::default()
        };
        assert!(matches!(v.rebase(Some(1), edit), Err(Stale::Conflict(_))));
        // A text this tab did not change leaves the current state.
        let edit = Edit {
            text: Some(TEXT.to_string()),
            ..Edit::default()
        };
        assert_eq!(v.rebase(Some(1), edit).unwrap().text, None);
    }

    #[test]
    fn unknown_versions_are_refused() {
        let mut v = versions();
        assert!(matches!(
            v.rebase(Some(7), Edit::default()),
            Err(Stale::Unknown(_))
        ));
        for i in 0..KEPT as u64 + 2 {
            v.record(TEXT, &knobs(&[("bias", i as f64)]));
        }
        assert!(matches!(
            v.rebase(Some(1), Edit::default()),
            Err(Stale::Unknown(_))
        ));
    }
}
