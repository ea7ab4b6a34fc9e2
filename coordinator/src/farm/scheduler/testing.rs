//! Set-up shared by the scheduler's unit tests: tiles of one value,
//! assignments taken, checks answered, frames rendered, jobs planned.

pub(super) use std::time::{Duration, Instant};

pub(super) use hypertexture::render::interleave::{WorkUnit, work_units};
pub(super) use hypertexture::{FrameRange, PixelFormat, Sample};
pub(super) use hypertexture_proto::{FailureKind, convert};

pub(super) use std::collections::HashMap;

pub(super) use super::state::*;
pub(super) use super::*;
pub(super) use crate::image::canvas::FrameImage;

pub(super) fn tile(unit: &WorkUnit, width: u32, value: f32) -> Vec<u8> {
    let samples = vec![Sample::from_array([value; Sample::CHANNELS]); unit.pixel_count(width)];
    convert::tile_to_wire(&samples, PixelFormat::Samples).to_vec()
}

pub(super) fn film(image: &FrameImage) -> &hypertexture::Film {
    match image {
        FrameImage::Film(film) => film,
        FrameImage::Srgb8 { .. } => panic!("a samples canvas gives a film"),
    }
}

pub(super) fn assign(s: &mut Scheduler, w: &str, now: Instant) -> (u64, WorkUnit) {
    match s.next(w, now).unwrap() {
        Next::Assign {
            assignment_id,
            unit,
            ..
        } => (assignment_id, unit),
        other => panic!("expected an assignment, got {other:?}"),
    }
}

/// Takes every check waiting and answers it with `outcome`.
pub(super) fn answer_checks(
    s: &mut Scheduler,
    outcome: &CheckOutcome,
    now: Instant,
) -> Vec<Verdict> {
    let mut verdicts = Vec::new();
    while let Some(check) = s.take_check() {
        verdicts.push(s.checked(&check, outcome.clone(), now));
    }
    verdicts
}

/// Renders every unit of the one-shot job with `w` (each tile `value`),
/// as long as it is handed units; returns how many it rendered.
pub(super) fn render_all(
    s: &mut Scheduler,
    w: &str,
    value: f32,
    width: u32,
    now: Instant,
) -> usize {
    let mut n = 0;
    while let Ok(Next::Assign {
        assignment_id,
        unit,
        ..
    }) = s.next(w, now)
    {
        let wire = convert::unit_to_wire(&unit);
        s.submit(
            w,
            assignment_id,
            Some(&wire),
            &tile(&unit, width, value),
            0,
            now,
        )
        .unwrap();
        n += 1;
    }
    n
}

/// Renders units with `w` until it is told to wait, each tile `value`.
pub(super) fn render_frame_part(
    s: &mut Scheduler,
    w: &str,
    value: f32,
    count: usize,
    now: Instant,
) {
    for _ in 0..count {
        let (id, unit) = assign(s, w, now);
        let wire = convert::unit_to_wire(&unit);
        s.submit(w, id, Some(&wire), &tile(&unit, 16, value), 0, now)
            .unwrap();
    }
}

pub(super) fn fail(
    s: &mut Scheduler,
    w: &str,
    id: u64,
    kind: FailureKind,
    now: Instant,
) -> Option<Counted> {
    s.fail(w, id, kind, &format!("{w} broke"), now).unwrap()
}

pub(super) fn plan(id: JobId, priority: i32, tags: &[&str]) -> JobPlan {
    JobPlan {
        id,
        priority,
        units: work_units(8, 8, 8, 4096),
        width: 8,
        height: 8,
        format: PixelFormat::Samples,
        frames: FrameRange::one(0),
        require_tags: tags.iter().map(|t| t.to_string()).collect(),
    }
}

pub(super) fn assign_job(s: &mut Scheduler, w: &str, now: Instant) -> (u64, JobId, WorkUnit) {
    match s.next(w, now).unwrap() {
        Next::Assign {
            assignment_id,
            job,
            unit,
            ..
        } => (assignment_id, job, unit),
        other => panic!("expected an assignment, got {other:?}"),
    }
}
