//! The service's store under load: `store_bench [DIR]` times 2,000 inserts of
//! a 16 KiB tile, fills the store to 10,000 tiles (plus 100 finished jobs),
//! then times opening it again, listing its jobs, counting its tiles and
//! reading one frame's tiles back, as a restart does. Run it in release:
//! `cargo run --release -p coordinator --example store_bench`.

use std::time::{Duration, Instant};

use coordinator::service::jobs::JobState;
use coordinator::service::store::Store;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    const PUTS: u32 = 2_000;
    const STORED: u32 = 10_000;
    const UNITS: u32 = 64;
    let given = std::env::args().nth(1).map(std::path::PathBuf::from);
    let dir = given.clone().unwrap_or_else(|| {
        std::env::temp_dir().join(format!("hypertexture-store-bench-{}", std::process::id()))
    });
    if dir.join("farm.sqlite").exists() {
        return Err(format!(
            "{} already holds a store: give an empty directory",
            dir.display()
        )
        .into());
    }
    let tile: Vec<u8> = (0..16384u32).map(|i| (i * 31 + 7) as u8).collect();
    for size in [1024, 16384] {
        const N: u32 = 20_000;
        let start = Instant::now();
        let mut sum = 0i64;
        for _ in 0..N {
            sum = sum.wrapping_add(coordinator::service::store::tile_checksum(
                std::hint::black_box(&tile[..size]),
            ));
        }
        println!(
            "tile_checksum of {size} bytes: {:.3} µs (sum {sum:x})",
            start.elapsed().as_secs_f64() * 1e6 / f64::from(N)
        );
    }
    {
        let store = Store::open(&dir)?;
        let job = store.insert_job("{}", 0, 0)?;
        let mut times = Vec::with_capacity(PUTS as usize);
        for i in 0..PUTS {
            let start = Instant::now();
            store.put_tile(job, i / UNITS, i % UNITS, &tile)?;
            times.push(start.elapsed());
        }
        times.sort();
        let total: Duration = times.iter().sum();
        let pct = |p: usize| times[(times.len() * p / 100).min(times.len() - 1)];
        println!(
            "put_tile 16 KiB × {PUTS}: mean {:.1} µs, median {:.1} µs, p99 {:.1} µs, max {:.1} µs",
            total.as_secs_f64() * 1e6 / f64::from(PUTS),
            pct(50).as_secs_f64() * 1e6,
            pct(99).as_secs_f64() * 1e6,
            times[times.len() - 1].as_secs_f64() * 1e6,
        );
        for i in PUTS..STORED {
            store.put_tile(job, i / UNITS, i % UNITS, &tile)?;
        }
        for _ in 0..100 {
            let j = store.insert_job(r#"{"scene":"x","out":"x_####.png"}"#, 0, 0)?;
            store.finish_frame(j, 0, "x_0000.png")?;
            store.set_state(j, JobState::Done, None)?;
        }
    }
    let size = std::fs::metadata(dir.join("farm.sqlite")).map_or(0, |m| m.len());
    let start = Instant::now();
    let store = Store::open(&dir)?;
    let opened = start.elapsed();
    let jobs = store.jobs()?;
    let listed = start.elapsed();
    let count = store.tile_count()?;
    let counted = start.elapsed();
    println!(
        "reopen with {count} tiles of 16 KiB ({:.1} MB file): open {:.2} ms, + jobs() of {} jobs {:.2} ms, + tile_count {:.2} ms",
        size as f64 / 1e6,
        opened.as_secs_f64() * 1e3,
        jobs.len(),
        listed.as_secs_f64() * 1e3,
        counted.as_secs_f64() * 1e3,
    );
    let start = Instant::now();
    let tiles = store.tiles(jobs[0].id, 3)?.tiles;
    println!(
        "tiles() of one frame ({} tiles): {:.2} ms",
        tiles.len(),
        start.elapsed().as_secs_f64() * 1e3
    );
    drop(store);
    if given.is_none() {
        std::fs::remove_dir_all(&dir)?;
    }
    Ok(())
}
