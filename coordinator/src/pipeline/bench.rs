//! `coordinator bench`: measured speedup of the farm on this machine, and a
//! simulation of larger farms from measured per-pixel and per-unit costs.

use std::collections::BinaryHeap;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use hypertexture::render::interleave::{DEFAULT_INTERLEAVE, farm_units};
use hypertexture::{Film, Overrides, Scene};

use crate::image::canvas::FrameImage;
use crate::{CoordinatorError, farm};

/// What to measure.
#[derive(Clone, Debug)]
pub struct BenchConfig {
    /// The scene.
    pub scene: PathBuf,
    /// The deliberately unbalanced scene for the simulation.
    pub unbalanced: PathBuf,
    /// Image size.
    pub width: Option<u32>,
    /// Image size.
    pub height: Option<u32>,
    /// Local worker counts to measure.
    pub workers: Vec<usize>,
    /// Simulated farm sizes.
    pub simulate: Vec<usize>,
    /// Rounds per farm size: an in-process render on every core, then the
    /// farm, taking turns, so that a machine's drift reaches both alike.
    pub rounds: usize,
    /// What the farm's tiles carry (8-bit sRGB for a PNG, every sample for an EXR).
    pub pixel_format: hypertexture::PixelFormat,
}

/// CPU seconds (user + system) of this process, or of its waited-for children.
fn cpu_seconds(who: libc::c_int) -> f64 {
    // SAFETY: getrusage only writes into the zeroed struct we pass.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    if unsafe { libc::getrusage(who, &mut usage) } != 0 {
        return 0.0;
    }
    let s = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 / 1e6;
    s(usage.ru_utime) + s(usage.ru_stime)
}

fn load(
    path: &std::path::Path,
    width: Option<u32>,
    height: Option<u32>,
) -> Result<(String, Scene), CoordinatorError> {
    let text = hypertexture::scene::read_text(path)?;
    let scene = Scene::from_text(
        &text,
        &path.display().to_string(),
        Overrides {
            width,
            height,
            ..Overrides::default()
        },
    )?;
    Ok((text, scene))
}

fn same(a: &Film, b: &Film) -> bool {
    a.pixels()
        .iter()
        .zip(b.pixels())
        .all(|(p, q)| p.to_array().map(f32::to_bits) == q.to_array().map(f32::to_bits))
}

/// Runs the benchmark and prints the tables on stdout.
pub fn run(config: &BenchConfig) -> Result<(), CoordinatorError> {
    let (text, scene) = load(&config.scene, config.width, config.height)?;
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let (serial_film, serial) = in_process_rows(config, &scene, cores)?;
    let encode_per_pixel = encode_cost(config.pixel_format, &serial_film);

    // As in `coordinator --local-workers N`: the farm is served on one thread.
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(CoordinatorError::Runtime)?;
    // The coordinator's known-answer probe is computed once per process: here,
    // before the farms, so that each farm's row shows what a frame costs.
    let probe_started = Instant::now();
    crate::farm::arithmetic_digest().map_err(crate::farm::FarmError::from)?;
    let probe_time = probe_started.elapsed().as_secs_f64();
    let reference = Reference {
        film: &serial_film,
        seconds: serial,
        cores,
    };
    let (call_points, render_thread_wait) =
        farm_rows(config, &runtime, (&text, &scene), &reference)?;
    println!();
    println!(
        "Each farm row: {} rounds, each an in-process render on {} threads then the farm, taking turns; wall is the farm's median, and \"against in-process\" the median of the rounds' ratios (in-process wall / farm wall). Wall: the render alone (first unit handed out to last tile in, like the in-process rows); in brackets with starting and stopping the worker processes. Efficiency: speedup / min(workers, cores). Coordinator CPU: its share of all CPU used (its own and its worker processes', from start-up to shut-down), and its own CPU time per round. What a unit costs a worker beyond rendering its pixels, charged by the simulation: encoding its tile, {:.1} ns per pixel (measured on the in-process image), and its calls (below). Not charged: the time the worker's render thread did not render in all, {:.2} ms (the first unit's wait, preemption on this machine, the last tile's trip). Not in the coordinator's rows: its known-answer probe, once per process before them, {:.1} ms (each worker process's own probe is in the workers' CPU).",
        config.rounds.max(1),
        cores,
        encode_per_pixel * 1e9,
        render_thread_wait * 1e3,
        probe_time * 1e3,
    );

    if config.simulate.is_empty() {
        return Ok(());
    }
    simulated_rows(
        config,
        &runtime,
        (&text, &scene),
        call_points,
        encode_per_pixel,
    )
}

/// The in-process render every farm is compared with: its image, its wall
/// time on one thread, and the cores of this machine.
struct Reference<'a> {
    film: &'a Film,
    seconds: f64,
    cores: usize,
}

/// Prints the title, the table's header and the in-process rows (one
/// thread, every core); returns the one-thread image and its wall seconds.
fn in_process_rows(
    config: &BenchConfig,
    scene: &Scene,
    cores: usize,
) -> Result<(Film, f64), CoordinatorError> {
    println!(
        "# coordinator bench: {} at {}×{}, {cores} cores",
        config.scene.display(),
        scene.width(),
        scene.height()
    );
    println!();
    println!(
        "| configuration | wall (s) | speedup | efficiency | against in-process, {cores} threads | coordinator CPU | tile bytes | imbalance (max/mean unit cost per pixel) | exact |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---|");

    let (serial_film, serial) = crate::pipeline::run::render_in_process(scene, 0, 1, false)?;
    let serial = serial.as_secs_f64();
    println!("| in-process, 1 thread | {serial:.3} | 1.00 | 100% | – | – | – | – | reference |");
    let (film, all) = crate::pipeline::run::render_in_process(scene, 0, cores, false)?;
    let all = all.as_secs_f64();
    println!(
        "| in-process, {cores} threads | {all:.3} | {:.2} | {:.0}% | 1 | – | – | – | {} |",
        serial / all,
        100.0 * serial / all / cores as f64,
        if same(&film, &serial_film) {
            "yes"
        } else {
            "NO"
        }
    );
    Ok((serial_film, serial))
}

/// Seconds a worker spends encoding a pixel of its tile (on its render
/// thread, counted in its unit's cost; in-process, the image is encoded
/// after the render): the fastest of three encodings of `film` in tiles of
/// at most a unit's pixels, as a worker encodes them.
fn encode_cost(format: hypertexture::PixelFormat, film: &Film) -> f64 {
    let tile = hypertexture::render::interleave::DEFAULT_MAX_UNIT_PIXELS as usize;
    (0..3)
        .map(|_| {
            let t = Instant::now();
            for chunk in film.pixels().chunks(tile) {
                std::hint::black_box(format.encode(chunk));
            }
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
        / film.pixels().len().max(1) as f64
}

/// The median of `values` (0 when empty).
fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    match values.len() {
        0 => 0.0,
        n if n % 2 == 1 => values[n / 2],
        n => (values[n / 2 - 1] + values[n / 2]) / 2.0,
    }
}

/// Prints a row per farm size of `config.workers`: `config.rounds` rounds of
/// an in-process render on every core then the farm, taking turns; the row
/// gives the farm's median wall and the median of the rounds' ratios.
/// Returns the (render µs, calls µs) of each tile of the 1-worker farms but
/// their first, and how long those farms' render thread did not render.
fn farm_rows(
    config: &BenchConfig,
    runtime: &tokio::runtime::Runtime,
    (text, scene): (&str, &Scene),
    reference: &Reference<'_>,
) -> Result<(Vec<(f64, u64)>, f64), CoordinatorError> {
    let (serial, cores) = (reference.seconds, reference.cores);
    let mut call_points: Vec<(f64, u64)> = Vec::new();
    let mut render_thread_wait = f64::INFINITY;
    for &n in &config.workers {
        let (mut walls, mut totals, mut ratios) = (Vec::new(), Vec::new(), Vec::new());
        let (mut own, mut workers, mut exact) = (0.0, 0.0, true);
        let mut last = None;
        for _ in 0..config.rounds.max(1) {
            let (_, in_process) = crate::pipeline::run::render_in_process(scene, 0, cores, false)?;
            let (self0, children0) = (
                cpu_seconds(libc::RUSAGE_SELF),
                cpu_seconds(libc::RUSAGE_CHILDREN),
            );
            let start = Instant::now();
            let report = farm_render(runtime, text, &config.scene, scene, config.pixel_format, n)?;
            totals.push(start.elapsed().as_secs_f64());
            // As for the in-process rows: the render itself, first unit out to last tile in.
            let wall = report.render_time.as_secs_f64();
            walls.push(wall);
            ratios.push(in_process.as_secs_f64() / wall);
            own += cpu_seconds(libc::RUSAGE_SELF) - self0;
            workers += cpu_seconds(libc::RUSAGE_CHILDREN) - children0;
            if n == 1 {
                call_points.extend(unit_call_points(&report));
                // For the record: how long its render thread did not render
                // (waiting for the first unit, preempted by the coordinator and
                // its own calls on this machine, the last tile's trip).
                let rendering = report.unit_costs.iter().map(|&c| c as f64).sum::<f64>() / 1e6;
                render_thread_wait = render_thread_wait.min((wall - rendering).max(0.0));
            }
            exact &= match &report.image {
                FrameImage::Film(film) => same(film, reference.film),
                image => image.srgb8() == reference.film.to_srgb8(),
            };
            last = Some(report);
        }
        let Some(report) = last else { continue };
        let costs: Vec<f64> = report.unit_costs.iter().map(|&c| c as f64).collect();
        let rounds = walls.len() as f64;
        let (wall, total) = (median(&mut walls), median(&mut totals));
        let speedup = serial / wall;
        println!(
            "| {n} worker process{} (loopback gRPC) | {wall:.3} ({total:.2} with start-up) | {speedup:.2} | {:.0}% | {:.3} | {:.2}% ({:.0} ms) | {} | {:.2} | {} |",
            if n == 1 { "" } else { "es" },
            100.0 * speedup / n.min(cores) as f64,
            median(&mut ratios),
            100.0 * own / (own + workers).max(1e-9),
            own * 1e3 / rounds,
            report.tile_bytes,
            imbalance(scene, n, &costs),
            if exact { "yes" } else { "NO" }
        );
    }
    // No 1-worker farm measured: nothing to report.
    Ok((
        call_points,
        if render_thread_wait.is_finite() {
            render_thread_wait
        } else {
            0.0
        },
    ))
}

/// The largest unit cost per pixel over the mean (0 without costs): units
/// differ in size (guided self-scheduling), so cost per pixel is compared.
fn imbalance(scene: &Scene, n: usize, costs: &[f64]) -> f64 {
    let sizes = farm_units(scene.width(), scene.height(), DEFAULT_INTERLEAVE, n);
    let per_pixel: Vec<f64> = costs
        .iter()
        .zip(&sizes)
        .map(|(c, u)| c / u.pixel_count(scene.width()).max(1) as f64)
        .collect();
    let mean = per_pixel.iter().sum::<f64>() / per_pixel.len().max(1) as f64;
    let max = per_pixel.iter().cloned().fold(0.0, f64::max);
    if mean > 0.0 { max / mean } else { 0.0 }
}

/// Fits what a unit's calls cost a worker and prints the simulated farms of
/// `config.simulate` sizes, for the scene and the unbalanced one.
fn simulated_rows(
    config: &BenchConfig,
    runtime: &tokio::runtime::Runtime,
    (text, scene): (&str, &Scene),
    mut call_points: Vec<(f64, u64)>,
    encode_per_pixel: f64,
) -> Result<(), CoordinatorError> {
    let on_farm = |text: &str, path: &std::path::Path, scene: &Scene, n: usize| {
        farm_render(runtime, text, path, scene, config.pixel_format, n)
    };
    // What a unit costs a worker beyond its pixels (rendering and encoding
    // them: the unit costs are its render thread's CPU): its async thread's
    // CPU (the calls), which on a worker whose render threads fill its cores
    // is taken from them. It grows with the time the unit renders (see
    // `UnitCalls`), so it is fitted over 1-worker farms of both scenes, whose
    // units render from about 1 ms to 10 ms.
    if !config.workers.contains(&1) {
        let report = on_farm(text, &config.scene, scene, 1)?;
        call_points.extend(unit_call_points(&report));
    }
    let (unbalanced_text, unbalanced) = load(&config.unbalanced, config.width, config.height)?;
    let report = on_farm(&unbalanced_text, &config.unbalanced, &unbalanced, 1)?;
    call_points.extend(unit_call_points(&report));
    let (render, call): (Vec<f64>, Vec<u64>) = call_points.into_iter().unzip();
    let calls = UnitCalls::fit(&render, &call);
    println!();
    println!(
        "What a unit costs a worker's async thread (its calls), fitted over the tiles of 1-worker farms of both scenes but their first ({} tiles): {:.3} ms + {:.1}% of the unit's render time (mean {:.3} ms). The simulation charges it to every unit; \"without the calls\" is the pull schedule with units costing their pixels (rendering and encoding) alone.",
        render.len(),
        calls.fixed * 1e3,
        calls.proportional * 1e2,
        calls.mean * 1e3,
    );
    println!();
    println!(
        "## Simulated farms (pull schedule vs contiguous blocks), from measured per-pixel costs"
    );
    println!();
    println!(
        "| scene | workers | units | pull speedup | pull efficiency | without the calls | blocks speedup | blocks efficiency |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|");
    for (name, s) in [("fur", scene), ("unbalanced (corner)", &unbalanced)] {
        let costs: Vec<f64> = pixel_costs(s)
            .into_iter()
            .map(|c| c + encode_per_pixel)
            .collect();
        for &w in &config.simulate {
            let sim = simulate(&costs, s.width(), s.height(), w, calls);
            let free = simulate(&costs, s.width(), s.height(), w, UnitCalls::default());
            println!(
                "| {name} | {w} | {} | {:.1} | {:.1}% | {:.1}% | {:.1} | {:.1}% |",
                sim.units,
                sim.pull_speedup,
                100.0 * sim.pull_speedup / w as f64,
                100.0 * free.pull_speedup / w as f64,
                sim.blocks_speedup,
                100.0 * sim.blocks_speedup / w as f64
            );
        }
    }
    Ok(())
}

/// Renders frame 0 of `scene` on a farm of `n` local worker processes of one
/// render thread each, served on `runtime`'s thread.
fn farm_render(
    runtime: &tokio::runtime::Runtime,
    text: &str,
    path: &std::path::Path,
    scene: &Scene,
    pixel_format: hypertexture::PixelFormat,
    n: usize,
) -> Result<farm::FarmReport, CoordinatorError> {
    let request = hypertexture::RenderRequest {
        pixel_format,
        ..hypertexture::RenderRequest::new(text, path.display().to_string())
    };
    let job = farm::FrameJob {
        frames: vec![farm::FrameOut {
            frame: 0,
            out: PathBuf::new(),
        }],
        metadata: std::sync::Arc::new(crate::image::output::ImageMetadata::new(scene, &request)),
        assets: farm::Asset::of_scene(scene, &request.scene_name)
            .map_err(CoordinatorError::Asset)?,
        request: request.with_size_of(scene),
    };
    let farm_config = farm::FarmConfig {
        listen: "127.0.0.1:0".parse().expect("a valid address"),
        token: None,
        lease: Duration::from_secs(10),
        worker_timeout: Duration::from_secs(60),
        local_workers: n,
        local_threads: 1,
        preview_every: None,
        tls: None,
        interleave: DEFAULT_INTERLEAVE,
        progress: false,
        gate: Default::default(),
        // The farm's own costs, without second renderings.
        verify: 0.0,
        allow_hosts: Vec::new(),
    };
    Ok(runtime.block_on(farm::render(job, farm_config))?)
}

/// A 1-worker farm's tiles as (render µs, calls µs), without the first, whose
/// calls include building the scene (once per scene on a LAN worker). One
/// worker renders the units in order, so the first is unit 0.
fn unit_call_points(report: &farm::FarmReport) -> impl Iterator<Item = (f64, u64)> + '_ {
    report
        .unit_costs
        .iter()
        .map(|&c| c as f64)
        .zip(report.unit_calls.iter().copied())
        .skip(1)
}

/// Seconds each pixel takes on one thread, row-major: the least of three
/// passes, so that a pass preempted by the OS (a spike of milliseconds on one
/// pixel, which would dominate a simulated 64-worker makespan) does not count.
pub fn pixel_costs(scene: &Scene) -> Vec<f64> {
    let pixels = scene.width() as usize * scene.height() as usize;
    let mut costs = vec![f64::INFINITY; pixels];
    for _ in 0..3 {
        for y in 0..scene.height() {
            for x in 0..scene.width() {
                let t = Instant::now();
                std::hint::black_box(hypertexture::render::render_pixel(scene, x, y, 0));
                let cost = &mut costs[(y * scene.width() + x) as usize];
                *cost = cost.min(t.elapsed().as_secs_f64());
            }
        }
    }
    costs
}

/// What a unit costs a worker's async thread (its calls: the tile out, the
/// next unit in), in seconds: `fixed + proportional × render`. Measured on a
/// 1-worker farm, it is not a constant per call: on this VM it grows with the
/// time the thread slept while the unit rendered (0.07 ms after a 2.7 ms
/// unit, 0.2 ms after a 9 ms one, with the same tile bytes), so a per-unit
/// mean would charge a farm of short units for long ones.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct UnitCalls {
    /// Seconds per unit.
    pub fixed: f64,
    /// Seconds per second of the unit's render.
    pub proportional: f64,
    /// The plain mean, seconds per unit (for the record).
    pub mean: f64,
}

impl UnitCalls {
    /// Least squares of the calls' CPU on the units' render CPU (both in
    /// microseconds, unit by unit), neither term below zero.
    pub fn fit(render_micros: &[f64], calls_micros: &[u64]) -> UnitCalls {
        let n = render_micros.len().min(calls_micros.len());
        if n == 0 {
            return UnitCalls::default();
        }
        let xs = &render_micros[..n];
        let ys: Vec<f64> = calls_micros[..n].iter().map(|&c| c as f64).collect();
        let (mx, my) = (
            xs.iter().sum::<f64>() / n as f64,
            ys.iter().sum::<f64>() / n as f64,
        );
        let sxx: f64 = xs.iter().map(|x| (x - mx) * (x - mx)).sum();
        let sxy: f64 = xs.iter().zip(&ys).map(|(x, y)| (x - mx) * (y - my)).sum();
        let slope = if sxx > 0.0 { (sxy / sxx).max(0.0) } else { 0.0 };
        let (proportional, fixed) = if my - slope * mx >= 0.0 {
            (slope, my - slope * mx)
        } else {
            // A negative intercept: all of it proportional, through the origin.
            let sxx0: f64 = xs.iter().map(|x| x * x).sum();
            let sxy0: f64 = xs.iter().zip(&ys).map(|(x, y)| x * y).sum();
            (if sxx0 > 0.0 { sxy0 / sxx0 } else { 0.0 }, 0.0)
        };
        UnitCalls {
            fixed: fixed / 1e6,
            proportional,
            mean: my / 1e6,
        }
    }

    /// A unit's whole cost to a worker, for `render` seconds of pixels.
    pub fn with_render(&self, render: f64) -> f64 {
        render * (1.0 + self.proportional) + self.fixed
    }
}

/// The outcome of one simulated farm.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Simulation {
    /// Units the image was cut into.
    pub units: usize,
    /// Serial time / makespan of the pull schedule.
    pub pull_speedup: f64,
    /// Serial time / makespan of W static contiguous row blocks.
    pub blocks_speedup: f64,
}

/// Simulates `workers` workers: pulling the farm's units in coarse-to-fine order
/// (each unit costing its pixels plus its calls), against W equal contiguous
/// bands of rows assigned statically.
pub fn simulate(
    costs: &[f64],
    width: u32,
    height: u32,
    workers: usize,
    calls: UnitCalls,
) -> Simulation {
    let serial: f64 = costs.iter().sum();
    // The farm's own units.
    let units = farm_units(width, height, DEFAULT_INTERLEAVE, workers);
    // Greedy list scheduling: the next unit goes to the worker free first.
    let mut free: BinaryHeap<std::cmp::Reverse<u64>> =
        (0..workers).map(|_| std::cmp::Reverse(0)).collect();
    let to_ns = |s: f64| (s * 1e9) as u64;
    let mut makespan = 0;
    for unit in &units {
        let cost = calls.with_render(
            unit.pixels(width)
                .map(|(x, y)| costs[(y * width + x) as usize])
                .sum::<f64>(),
        );
        let std::cmp::Reverse(start) = free.pop().unwrap_or(std::cmp::Reverse(0));
        let end = start + to_ns(cost);
        makespan = makespan.max(end);
        free.push(std::cmp::Reverse(end));
    }
    let pull = serial / (makespan as f64 / 1e9);
    // Contiguous blocks: worker i gets rows [i·h/W, (i+1)·h/W).
    let rows: Vec<f64> = costs
        .chunks(width as usize)
        .map(|r| r.iter().sum())
        .collect();
    let mut worst: f64 = 0.0;
    for i in 0..workers {
        let (a, b) = (
            i * height as usize / workers,
            (i + 1) * height as usize / workers,
        );
        worst = worst.max(calls.with_render(rows[a..b].iter().sum::<f64>()));
    }
    Simulation {
        units: units.len(),
        pull_speedup: pull,
        blocks_speedup: serial / worst,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_cost_simulates_linear_speedup_both_ways() {
        let costs = vec![1e-5; 64 * 64];
        let sim = simulate(&costs, 64, 64, 8, UnitCalls::default());
        assert!((sim.pull_speedup - 8.0).abs() < 0.01, "{sim:?}");
        assert!((sim.blocks_speedup - 8.0).abs() < 0.01, "{sim:?}");
    }

    #[test]
    fn unit_calls_fit_a_line_and_charge_it() {
        let render = [1000.0, 2000.0, 4000.0, 8000.0];
        let calls = [30, 50, 90, 170];
        let fit = UnitCalls::fit(&render, &calls);
        assert!((fit.fixed - 10e-6).abs() < 1e-9, "{fit:?}");
        assert!((fit.proportional - 0.02).abs() < 1e-9, "{fit:?}");
        assert!((fit.with_render(1e-3) - 1.03e-3).abs() < 1e-12, "{fit:?}");
        // More calls for shorter units: no negative slope, the mean stays fixed.
        let fit = UnitCalls::fit(&render, &[90, 80, 70, 60]);
        assert_eq!(fit.proportional, 0.0);
        assert!((fit.fixed - 75e-6).abs() < 1e-9, "{fit:?}");
        assert_eq!(UnitCalls::fit(&[], &[]), UnitCalls::default());
    }

    #[test]
    fn a_costly_corner_ruins_blocks_but_not_the_interleave() {
        let mut costs = vec![1e-6; 64 * 64];
        for y in 0..16 {
            for x in 0..16 {
                costs[y * 64 + x] = 1e-4;
            }
        }
        let sim = simulate(&costs, 64, 64, 4, UnitCalls::default());
        assert!(sim.pull_speedup > 3.8, "{sim:?}");
        assert!(sim.blocks_speedup < 1.5, "{sim:?}");
    }
}
