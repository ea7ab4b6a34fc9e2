//! Interleaved pixel sets: how an image is split among processors.
//!
//! As on the paper's 64-processor Pixel Machine, each processor computes an
//! interleaved subset of the screen: with a B×B interleave, pixel (x, y) belongs to
//! set `(y mod B)·B + (x mod B)`. Every set is spread evenly over the image, so each
//! costs about the same (load balance) and any one of them is a complete
//! low-resolution image. Sets are further cut into bands of rows ([`WorkUnit`]) so
//! that there are many small units per worker, and handed out coarse to fine in
//! the order of a Bayer matrix: after the first set the whole image exists at 1/B
//! resolution, after the first four at 2/B, and so on (like Adam7).

/// The default interleave: 8×8, 64 pixel sets, as the paper's 64 processors.
pub const DEFAULT_INTERLEAVE: u32 = 8;

/// The default largest unit, in pixels (a tile of 4096 samples is ~150 KB on the wire).
pub const DEFAULT_MAX_UNIT_PIXELS: u32 = 4096;

/// One interleaved pixel set of an image.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct PixelSet {
    /// The interleave B (sets are B×B).
    pub interleave: u32,
    /// The set index `(y mod B)·B + (x mod B)`, in `0..B²`.
    pub index: u32,
}

impl PixelSet {
    /// The set pixel (x, y) belongs to.
    pub fn of_pixel(interleave: u32, x: u32, y: u32) -> PixelSet {
        PixelSet {
            interleave,
            index: (y % interleave) * interleave + (x % interleave),
        }
    }

    /// The offset (x mod B, y mod B) shared by the set's pixels.
    pub fn offset(&self) -> (u32, u32) {
        (self.index % self.interleave, self.index / self.interleave)
    }

    /// Columns of the set in an image `width` wide.
    pub fn columns(&self, width: u32) -> u32 {
        let (ox, _) = self.offset();
        if ox >= width {
            0
        } else {
            (width - ox).div_ceil(self.interleave)
        }
    }

    /// Rows of the set in an image `height` high.
    pub fn rows(&self, height: u32) -> u32 {
        let (_, oy) = self.offset();
        if oy >= height {
            0
        } else {
            (height - oy).div_ceil(self.interleave)
        }
    }
}

/// A unit of work: the rows `first_row + i·row_stride` (i < `row_count`) of one
/// pixel set, where set row r is image row `offset.y + r·B`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct WorkUnit {
    /// The set.
    pub set: PixelSet,
    /// First set row.
    pub first_row: u32,
    /// Number of set rows.
    pub row_count: u32,
    /// Distance between the unit's set rows (1: a contiguous band).
    pub row_stride: u32,
}

impl WorkUnit {
    /// The unit's pixels in image coordinates, row-major: the order of its tile.
    pub fn pixels(&self, width: u32) -> impl Iterator<Item = (u32, u32)> + '_ {
        let (ox, oy) = self.set.offset();
        let b = self.set.interleave;
        let columns = self.set.columns(width);
        let (first, stride) = (self.first_row, self.row_stride);
        (0..self.row_count).flat_map(move |i| {
            let r = first + i * stride;
            (0..columns).map(move |c| (ox + c * b, oy + r * b))
        })
    }

    /// Number of pixels in the unit (the length of its tile).
    pub fn pixel_count(&self, width: u32) -> usize {
        self.set.columns(width) as usize * self.row_count as usize
    }
}

/// The rank of (x, y) in the B×B Bayer matrix (B a power of two): every prefix of
/// length 4^k of the ranks is a regular lattice of spacing B / 2^k.
pub fn bayer_rank(interleave: u32, x: u32, y: u32) -> u32 {
    let bits = interleave.trailing_zeros();
    let mut rank = 0;
    for bit in 0..bits {
        // The coarsest level (highest bit of the rank) is decided by the lowest bit of
        // x and y: (0,0) first, then (1,1), (1,0), (0,1) — the classic dither order.
        let xb = (x >> bit) & 1;
        let yb = (y >> bit) & 1;
        let digit = match (xb, yb) {
            (0, 0) => 0,
            (1, 1) => 1,
            (1, 0) => 2,
            _ => 3,
        };
        rank |= digit << (2 * (bits - 1 - bit));
    }
    rank
}

/// The farm's units for about `workers` workers, in coarse-to-fine order.
///
/// - **Under 8 workers** (a machine's local workers, which share its cores
///   with the coordinator and each other, so that unit times vary): about 32
///   units per worker, 1/(32·workers) of the image (1024 to
///   [`DEFAULT_MAX_UNIT_PIXELS`] pixels), and the last quarter of the sets in
///   half-size units, so that the workers finish together.
/// - **8 workers or more:** equal units, as large as the cap allows and at
///   least one per worker (`pixels / workers` when that is smaller), of a
///   finer interleave than `interleave` beyond 256 workers
///   ([`large_farm_interleave`]). Every unit is an interleaved sample of the
///   whole image, so units of equal size cost the same: within ±2% for both
///   the fur and the one-dense-corner scene at 512² (`coordinator bench`).
///   Finer units then balance nothing; they only add calls, about 0.05 ms of
///   a worker's CPU each on our VM. At 64 workers on the 512² corner frame
///   (3.4 ms per worker), 448 units, finer at the end, simulated 86–95%
///   efficiency; whole sets, 96–97% (docs/benchmark-log.md, "equal units for
///   large farms"). At 1,024 workers on the 2048² corner frame (1.7 ms per
///   worker), two units per worker simulated 85–90% against 92–95% for one.
///   A straggler is covered by the scheduler's speculative duplicates.
pub fn farm_units(width: u32, height: u32, interleave: u32, workers: usize) -> Vec<WorkUnit> {
    let pixels = u64::from(width) * u64::from(height);
    let cap = u64::from(DEFAULT_MAX_UNIT_PIXELS);
    let workers = workers.max(1) as u64;
    let (coarse, fine) = if workers < 8 {
        let coarse = (pixels / (32 * workers)).clamp(1024, cap) as u32;
        (coarse, coarse / 2)
    } else {
        // At least one pixel: `set_units` makes it one set row.
        let equal = (pixels / workers).clamp(1, cap) as u32;
        (equal, equal)
    };
    let interleave = if workers < 8 {
        interleave
    } else {
        large_farm_interleave(interleave, width, height, workers)
    };
    let sets = interleave * interleave;
    let tail_from = sets - sets / 4;
    let mut units = Vec::new();
    for (rank, set) in sets_in_order(interleave).into_iter().enumerate() {
        let max = if (rank as u32) < tail_from {
            coarse
        } else {
            fine
        };
        units.extend(set_units(set, width, height, max));
    }
    units
}

/// The interleave of a farm of `workers` (8 or more): `interleave`, doubled
/// while there are fewer than a set per 4 workers (up to 64, and while a set
/// keeps 8×8 pixels). A unit then samples the image on a finer lattice, so that
/// units of equal size cost more nearly the same where the cost is in one
/// place: for the one-dense-corner scene at 2048² on 1,024 workers, B = 16
/// makes the largest unit 2.5% closer to the mean than B = 8
/// (`coordinator bench --simulate 1024`). Farms of up to 256 workers keep
/// B = 8, and the order stays coarse to fine.
fn large_farm_interleave(interleave: u32, width: u32, height: u32, workers: u64) -> u32 {
    let mut b = interleave;
    while b < 64 && u64::from(b * b) * 4 < workers && b * 2 * 8 <= width.min(height) {
        b *= 2;
    }
    b
}

/// The B² sets in coarse-to-fine (Bayer) order.
fn sets_in_order(interleave: u32) -> Vec<PixelSet> {
    let mut sets: Vec<PixelSet> = (0..interleave * interleave)
        .map(|index| PixelSet { interleave, index })
        .collect();
    sets.sort_by_key(|s| {
        let (x, y) = s.offset();
        bayer_rank(interleave, x, y)
    });
    sets
}

/// A set cut into K units of at most `max_unit_pixels` pixels (at least one row),
/// unit k taking set rows k, k + K, k + 2K, …
fn set_units(
    set: PixelSet,
    width: u32,
    height: u32,
    max_unit_pixels: u32,
) -> impl Iterator<Item = WorkUnit> {
    let (columns, rows) = (set.columns(width), set.rows(height));
    let k = if columns == 0 || rows == 0 {
        0
    } else {
        rows.div_ceil((max_unit_pixels / columns).clamp(1, rows))
    };
    (0..k).map(move |first_row| WorkUnit {
        set,
        first_row,
        row_count: (rows - first_row).div_ceil(k),
        row_stride: k,
    })
}

/// The work units of a `width × height` image, in coarse-to-fine order: sets by
/// Bayer rank, each cut into K units of at most `max_unit_pixels` pixels (at
/// least one row), unit k taking set rows k, k + K, k + 2K, …
/// `interleave` must be a power of two from 1 to 64.
pub fn work_units(width: u32, height: u32, interleave: u32, max_unit_pixels: u32) -> Vec<WorkUnit> {
    assert!(
        interleave.is_power_of_two() && interleave <= 64,
        "interleave must be a power of two ≤ 64"
    );
    sets_in_order(interleave)
        .into_iter()
        .flat_map(|set| set_units(set, width, height, max_unit_pixels))
        .collect()
}

/// Checks that `units` cover every pixel of a `width × height` image exactly
/// once: one interleave B for all, and every row of every one of the B×B sets
/// in exactly one unit (a unit takes whole set rows). The farm relies on it:
/// a pixel in no unit would never be rendered, one in two would be rendered
/// twice. The error names the first row at fault.
pub fn check_partition(units: &[WorkUnit], width: u32, height: u32) -> Result<(), String> {
    let Some(first) = units.first() else {
        return Err("no units".into());
    };
    let b = first.set.interleave;
    if !b.is_power_of_two() || b > 64 {
        return Err(format!("interleave {b} is not a power of two up to 64"));
    }
    let sets = (b * b) as usize;
    let rows_per_set = height.div_ceil(b) as usize;
    let mut covered = vec![false; sets * rows_per_set];
    for u in units {
        if u.set.interleave != b || u.set.index as usize >= sets {
            return Err(format!(
                "a unit of pixel set {} of {}×{} among units of {b}×{b}",
                u.set.index, u.set.interleave, u.set.interleave
            ));
        }
        let rows = u.set.rows(height);
        for i in 0..u.row_count {
            let r = u64::from(u.first_row) + u64::from(i) * u64::from(u.row_stride);
            if r >= u64::from(rows) {
                return Err(format!(
                    "a unit of pixel set {} takes row {r}, beyond the set's {rows} rows",
                    u.set.index
                ));
            }
            let slot = &mut covered[u.set.index as usize * rows_per_set + r as usize];
            if std::mem::replace(slot, true) {
                return Err(format!(
                    "row {r} of pixel set {} is in two units",
                    u.set.index
                ));
            }
        }
    }
    for index in 0..sets as u32 {
        let set = PixelSet {
            interleave: b,
            index,
        };
        if set.columns(width) == 0 {
            continue;
        }
        if let Some(r) =
            (0..set.rows(height) as usize).find(|&r| !covered[index as usize * rows_per_set + r])
        {
            return Err(format!("row {r} of pixel set {index} is in no unit"));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_large_farm_samples_the_image_on_a_finer_lattice() {
        // Up to 256 workers, the interleave asked for; beyond, doubled while
        // there are fewer than a set per 4 workers and a set keeps 8×8 pixels.
        let interleave_of = |w: u32, h: u32, workers: usize| {
            let units = farm_units(w, h, 8, workers);
            assert_eq!(check_partition(&units, w, h), Ok(()), "{w}×{h}, {workers}");
            let b = units[0].set.interleave;
            assert!(units.iter().all(|u| u.set.interleave == b));
            b
        };
        assert_eq!(interleave_of(2048, 2048, 64), 8);
        assert_eq!(interleave_of(2048, 2048, 256), 8);
        assert_eq!(interleave_of(2048, 2048, 1024), 16);
        assert_eq!(interleave_of(2048, 2048, 4096), 32);
        assert_eq!(interleave_of(2048, 2048, 100_000), 64);
        assert_eq!(interleave_of(256, 256, 4096), 32);
        assert_eq!(interleave_of(100, 37, 4096), 8);
        // Still one unit per worker, coarse to fine: the first set is the
        // lattice through (0, 0).
        let units = farm_units(2048, 2048, 8, 1024);
        assert_eq!(units.len(), 1024);
        assert_eq!(units[0].set.offset(), (0, 0));
    }

    #[test]
    fn a_partition_must_cover_every_pixel_once() {
        for (w, h, b, workers) in [(16, 16, 8, 4), (33, 17, 4, 3), (5, 7, 8, 1), (64, 64, 1, 2)] {
            let units = farm_units(w, h, b, workers);
            assert_eq!(check_partition(&units, w, h), Ok(()), "{w}×{h} B={b}");
        }
        let units = work_units(16, 16, 8, 4096);
        let skipped = &units[1..];
        assert!(
            check_partition(skipped, 16, 16)
                .unwrap_err()
                .contains("is in no unit")
        );
        let mut twice = units.clone();
        twice.push(units[0]);
        assert!(
            check_partition(&twice, 16, 16)
                .unwrap_err()
                .contains("in two units")
        );
        let mut short = units.clone();
        short[0].row_count -= 1;
        assert!(check_partition(&short, 16, 16).is_err());
        let mut beyond = units;
        beyond[0].row_count += 1;
        assert!(
            check_partition(&beyond, 16, 16)
                .unwrap_err()
                .contains("beyond")
        );
        assert!(check_partition(&[], 16, 16).is_err());
    }

    #[test]
    fn set_of_pixel_is_the_papers_interleave() {
        assert_eq!(PixelSet::of_pixel(8, 0, 0).index, 0);
        assert_eq!(PixelSet::of_pixel(8, 9, 0).index, 1);
        assert_eq!(PixelSet::of_pixel(8, 3, 10).index, 2 * 8 + 3);
        assert_eq!(PixelSet::of_pixel(8, 3, 10).offset(), (3, 2));
    }

    #[test]
    fn units_cover_every_pixel_exactly_once() {
        for (w, h, b, max) in [
            (37, 23, 8, 7),
            (64, 64, 8, 4096),
            (5, 3, 8, 1),
            (100, 1, 4, 10),
            (1, 1, 8, 4096),
        ] {
            let mut seen = vec![0u8; (w * h) as usize];
            for unit in work_units(w, h, b, max) {
                assert!(unit.pixel_count(w) <= max.max(unit.set.columns(w)) as usize);
                assert!(unit.row_count >= 1 && unit.first_row < unit.row_stride);
                let pixels: Vec<_> = unit.pixels(w).collect();
                assert_eq!(pixels.len(), unit.pixel_count(w));
                for (x, y) in pixels {
                    assert_eq!(PixelSet::of_pixel(b, x, y), unit.set);
                    seen[(y * w + x) as usize] += 1;
                }
            }
            assert!(seen.iter().all(|&n| n == 1), "{w}×{h} B={b}");
        }
    }

    #[test]
    fn order_is_coarse_to_fine() {
        let order: Vec<(u32, u32)> = {
            let mut sets: Vec<_> = (0..64u32).map(|i| (i % 8, i / 8)).collect();
            sets.sort_by_key(|&(x, y)| bayer_rank(8, x, y));
            sets
        };
        assert_eq!(order[0], (0, 0));
        // The first 4 sets form the lattice of spacing 4, the first 16 of spacing 2.
        for (k, spacing) in [(4, 4), (16, 2), (64, 1)] {
            let prefix = &order[..k];
            for &(x, y) in prefix {
                assert_eq!((x % spacing, y % spacing), (0, 0), "prefix {k}: {prefix:?}");
            }
        }
        let ranks: std::collections::BTreeSet<_> =
            (0..64).map(|i| bayer_rank(8, i % 8, i / 8)).collect();
        assert_eq!(ranks.len(), 64);
        // And units follow that order.
        let units = work_units(64, 64, 8, 4096);
        assert_eq!(units.len(), 64);
        assert_eq!(units[0].set.offset(), (0, 0));
        assert_eq!(units[1].set.offset(), (4, 4));
    }

    #[test]
    fn farm_units_cover_the_image_and_suit_the_farm() {
        for (w, h, b) in [(512, 512, 8), (37, 23, 8), (64, 48, 4), (1, 1, 8)] {
            for workers in [0, 1, 2, 7, 8, 64, 1000] {
                let units = farm_units(w, h, b, workers);
                let mut seen = vec![0u8; (w * h) as usize];
                for unit in &units {
                    for (x, y) in unit.pixels(w) {
                        seen[(y * w + x) as usize] += 1;
                    }
                }
                assert!(seen.iter().all(|&n| n == 1), "{w}×{h}, {workers} workers");
            }
        }
        // 8 workers or more: whole sets (the cap), at least one unit each.
        let units = farm_units(512, 512, 8, 8);
        assert!(units.iter().all(|u| u.pixel_count(512) == 4096));
        assert_eq!(units.len(), 64);
        let units = farm_units(512, 512, 8, 256);
        assert!(units.iter().all(|u| u.pixel_count(512) == 1024));
        assert_eq!(units.len(), 256);
        let units = farm_units(2048, 2048, 8, 64);
        assert!(units.iter().all(|u| u.pixel_count(2048) == 4096));
        // A 2-worker farm: whole sets, then half sets.
        let units = farm_units(512, 512, 8, 2);
        assert_eq!(units[0].pixel_count(512), 4096);
        assert_eq!(units.last().unwrap().pixel_count(512), 2048);
        assert_eq!(units.len(), 48 + 16 * 2);
    }
}
