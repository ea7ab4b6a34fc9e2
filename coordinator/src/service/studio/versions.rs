//! One state owned by the server, for every tab: the scene text and knob
//! values carry a *version*, one more per edit that changes them. A tab's
//! edit names the version it was made on; when another tab edited since, the
//! edit is merged onto the current version if it touches other values (other
//! knobs, other numbers of the text, other lines), and refused as a conflict
//! when it touches the same one. A stale tab never silently undoes another.
//!
//! The versions also hold the undo history, one for every tab: undo is an
//! edit that sets the text and values back to the state before the last
//! step, byte for byte, and is a new version like any edit (so every tab
//! follows it); redo steps forward again; a new edit after an undo drops
//! what redo held. A step is one gesture of one tab (a slider's drag, an
//! orbit of the camera, a burst of typing: the edits that name the same tab
//! and gesture), or one edit that names none.

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
    /// The states undo goes back to, the next one last (at most [`KEPT`]).
    undo: VecDeque<Version>,
    /// The states redo goes forward to, the next one last.
    redo: VecDeque<Version>,
    /// The tab and gesture of the step the last edit belongs to.
    gesture: Option<(String, String)>,
    /// The version of the text as opened.
    opened: u64,
}

/// What made a new state, for the undo history.
#[derive(Clone, Debug, PartialEq)]
pub enum Origin {
    /// An edit: it continues the last step when it names the same tab and
    /// gesture as the edit before it, and starts a step otherwise.
    Edit {
        tab: Option<String>,
        gesture: Option<String>,
    },
    /// Undo: the state is [`Versions::undo_to`]'s.
    Undo,
    /// Redo: the state is [`Versions::redo_to`]'s.
    Redo,
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
            undo: VecDeque::new(),
            redo: VecDeque::new(),
            gesture: None,
            opened: 0,
        }
    }

    /// Another scene's text is opened: a history of its own (nothing to undo
    /// or redo, no older version to merge with), its first version one past
    /// the current, so that every tab takes it as newer.
    pub fn restart(&mut self, shown: &str) {
        let number = self.current().number + 1;
        *self = Versions::new(shown);
        self.kept[0].number = number;
        self.opened = number;
    }

    pub fn current(&self) -> &Version {
        self.kept.back().expect("a version is always kept")
    }

    /// Records the state after an edit that names no gesture (a step of its
    /// own): a new version when the text or the knob values changed. Returns
    /// whether it did.
    #[cfg(test)]
    pub fn record(&mut self, shown: &str, knobs: &BTreeMap<String, f64>) -> bool {
        let origin = Origin::Edit {
            tab: None,
            gesture: None,
        };
        self.record_as(shown, knobs, origin)
    }

    /// [`Versions::record`] of a state made by `origin`, which moves the undo
    /// history: an edit that starts a step puts the state before it on the
    /// undo list and empties the redo list (the first build of the text as
    /// opened, which only fills in the knob values, is no step); an undo moves the state before it
    /// to the redo list, a redo to the undo list.
    pub fn record_as(
        &mut self,
        shown: &str,
        knobs: &BTreeMap<String, f64>,
        origin: Origin,
    ) -> bool {
        let now = self.current();
        let unchanged = now.shown == shown && now.knobs == *knobs;
        let before = now.clone();
        match origin {
            Origin::Edit { tab, gesture } => {
                if unchanged {
                    return false;
                }
                let step = tab.zip(gesture);
                let first_build = before.number == self.opened && before.shown == shown;
                if (step.is_none() || step != self.gesture) && !first_build {
                    push_bounded(&mut self.undo, before.clone());
                }
                self.gesture = step;
                self.redo.clear();
            }
            Origin::Undo | Origin::Redo => {
                let (from, to) = if origin == Origin::Undo {
                    (&mut self.undo, &mut self.redo)
                } else {
                    (&mut self.redo, &mut self.undo)
                };
                from.pop_back();
                if !unchanged {
                    push_bounded(to, before.clone());
                }
                self.gesture = None;
            }
        }
        if unchanged {
            return false;
        }
        push_bounded(
            &mut self.kept,
            Version {
                number: before.number + 1,
                shown: shown.to_string(),
                knobs: knobs.clone(),
            },
        );
        true
    }

    /// The state an undo sets back, if any.
    pub fn undo_to(&self) -> Option<&Version> {
        self.undo.back()
    }

    /// The state a redo sets again, if any.
    pub fn redo_to(&self) -> Option<&Version> {
        self.redo.back()
    }

    /// How many steps undo and redo can take.
    pub fn steps(&self) -> (usize, usize) {
        (self.undo.len(), self.redo.len())
    }

    /// Version `base` (none: the current one), if it is kept.
    pub fn at(&self, base: Option<u64>) -> Result<&Version, Stale> {
        let now = self.current();
        let Some(base) = base.filter(|&b| b != now.number) else {
            return Ok(now);
        };
        if base > now.number {
            return Err(Stale::Unknown(format!(
                "version {base} is not known: the studio is at version {}",
                now.number
            )));
        }
        self.kept.iter().find(|v| v.number == base).ok_or_else(|| {
            Stale::Unknown(format!(
                "the edit was made on version {base}, which the studio no longer keeps \
                     (it is at version {}): the page shows the current state",
                now.number
            ))
        })
    }

    /// `edit`, made on version `base` (none: on the current one), as an edit
    /// of the current version.
    pub fn rebase(&self, base: Option<u64>, edit: Edit) -> Result<Edit, Stale> {
        let now = self.current();
        let then = self.at(base)?;
        if then.number == now.number {
            return Ok(edit);
        }
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

/// Adds `version` last, dropping the first beyond [`KEPT`].
fn push_bounded(list: &mut VecDeque<Version>, version: Version) {
    list.push_back(version);
    while list.len() > KEPT {
        list.pop_front();
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
        // A structural edit is made on the text of the version it names.
        let b3 = TEXT.replace("b: 2.0", "b: 3.0");
        v.record(&b3, &knobs(&[("bias", 0.3), ("gain", 0.9)]));
        assert_eq!(v.at(Some(1)).unwrap().shown, TEXT);
        assert_eq!(v.at(None).unwrap().shown, b3);
        assert_eq!(v.at(Some(2)).unwrap().number, 2);
        assert!(matches!(v.at(Some(3)), Err(Stale::Unknown(_))));
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

    #[test]
    fn another_scene_starts_a_history_of_its_own_at_a_newer_version() {
        let mut v = versions();
        v.record(&TEXT.replace("b: 2.0", "b: 3.0"), &knobs(&[("bias", 0.3)]));
        assert_eq!(v.steps(), (1, 0));
        v.restart("Other()");
        assert_eq!(v.current().number, 3);
        assert_eq!(v.steps(), (0, 0), "nothing of the scene before");
        assert!(v.record("Other()", &knobs(&[("k", 1.0)])));
        assert_eq!(v.steps(), (0, 0), "its first build is no step");
        assert!(matches!(v.at(Some(2)), Err(Stale::Unknown(_))));
        assert!(v.record("Other(x)", &knobs(&[("k", 1.0)])));
        assert_eq!(v.undo_to().unwrap().shown, "Other()");
    }

    fn edit(tab: &str, gesture: &str) -> Origin {
        Origin::Edit {
            tab: Some(tab.to_string()),
            gesture: Some(gesture.to_string()),
        }
    }

    /// Undoes once: the state it sets back, recorded as the undo.
    fn undo(v: &mut Versions) -> String {
        let back = v.undo_to().expect("a step to undo").clone();
        assert!(v.record_as(&back.shown, &back.knobs, Origin::Undo));
        back.shown
    }

    fn redo(v: &mut Versions) -> String {
        let again = v.redo_to().expect("a step to redo").clone();
        assert!(v.record_as(&again.shown, &again.knobs, Origin::Redo));
        again.shown
    }

    #[test]
    fn a_gesture_is_one_step_and_undo_gives_the_text_back_byte_for_byte() {
        let opened = "Scene(\n    a: 1.000,  // odd spacing kept\n\tb: 2.0,\n)\n";
        let mut v = Versions::new(opened);
        let gains = knobs(&[("gain", 0.5)]);
        // The first build: the text as opened is not a step of its own.
        assert!(v.record(opened, &gains));
        assert_eq!(v.steps(), (0, 0));
        // A slider's drag: many edits of one gesture, one step.
        let dragged = opened.replace("a: 1.000", "a: 1.5");
        for a in ["1.1", "1.3", "1.5"] {
            let text = opened.replace("a: 1.000", &format!("a: {a}"));
            assert!(v.record_as(&text, &gains, edit("tab A", "1")));
        }
        // Another gesture of the same tab (a camera orbit), then a text edit
        // of another tab.
        let orbited = dragged.replace("b: 2.0", "b: 2.25");
        v.record_as(&orbited, &gains, edit("tab A", "2"));
        let typed = format!("// typed\n{orbited}");
        v.record_as(&typed, &gains, edit("tab B", "1"));
        assert_eq!(v.steps(), (3, 0));

        assert_eq!(undo(&mut v), orbited);
        assert_eq!(undo(&mut v), dragged);
        assert_eq!(undo(&mut v), opened);
        assert_eq!(v.current().shown.as_bytes(), opened.as_bytes());
        assert_eq!(v.current().knobs, gains);
        assert_eq!(v.steps(), (0, 3));
        assert_eq!(v.undo_to(), None, "nothing before the text as opened");
        // Each undo is a version of its own: every tab follows it.
        assert_eq!(v.current().number, 9);

        assert_eq!(redo(&mut v), dragged);
        assert_eq!(redo(&mut v), orbited);
        assert_eq!(redo(&mut v), typed);
        assert_eq!(v.steps(), (3, 0));
        assert_eq!(v.current().shown, typed);

        // A scene without knobs: its first build makes no version, and the
        // first edit steps back to the text as opened.
        let mut v = Versions::new(opened);
        assert!(!v.record(opened, &BTreeMap::new()));
        v.record_as(&dragged, &BTreeMap::new(), edit("tab A", "1"));
        assert_eq!(undo(&mut v), opened);
    }

    #[test]
    fn a_new_edit_after_an_undo_drops_the_redo_list() {
        let mut v = versions();
        let b3 = TEXT.replace("b: 2.0", "b: 3.0");
        v.record_as(&b3, &knobs(&[("bias", 0.3)]), edit("A", "1"));
        v.record_as(&b3, &knobs(&[("bias", 0.4)]), edit("A", "2"));
        undo(&mut v);
        assert_eq!(v.steps(), (1, 1));
        // The same gesture after an undo is a new step.
        v.record_as(&b3, &knobs(&[("bias", 0.5)]), edit("A", "2"));
        assert_eq!(v.steps(), (2, 0));
        assert_eq!(v.redo_to(), None);
        // An unchanged state moves nothing.
        assert!(!v.record_as(&b3, &knobs(&[("bias", 0.5)]), edit("A", "3")));
        assert_eq!(v.steps(), (2, 0));
        // Edits that name no gesture are a step each.
        v.record(&b3, &knobs(&[("bias", 0.6)]));
        v.record(&b3, &knobs(&[("bias", 0.7)]));
        assert_eq!(v.steps(), (4, 0));
    }

    #[test]
    fn the_history_keeps_the_last_kept_steps() {
        let mut v = versions();
        for i in 0..KEPT as u64 + 10 {
            v.record(TEXT, &knobs(&[("bias", i as f64)]));
        }
        assert_eq!(v.steps(), (KEPT, 0));
        let mut last = None;
        while v.undo_to().is_some() {
            undo(&mut v);
            last = Some(v.current().knobs.clone());
        }
        assert_eq!(
            last,
            Some(knobs(&[("bias", 9.0)])),
            "the oldest steps go first"
        );
        assert_eq!(v.steps(), (0, KEPT));
    }
}
