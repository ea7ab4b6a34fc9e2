//! A mesh's distance field: its build time, memory and error against the
//! exact distance over the soft region.
//!
//! `cargo run --release -p hypertexture --example mesh_field -- OBJ SOFTNESS [VOXEL...]`
//! (`OBJ` a file, or `icosphere:LEVELS` for a subdivided, displaced
//! icosphere of 20·4^LEVELS triangles; each `VOXEL` a length, default
//! softness/4; `POINTS=n` in the environment measures the error at n points
//! of the soft region, default 200000). One core: `taskset -c 0 ...`.

use std::time::Instant;

use hypertexture::mesh::{Band, BandSpec, DEFAULT_MAX_FIELD_BYTES, Mesh};

fn main() -> std::process::ExitCode {
    match run() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("mesh_field: {e}");
            std::process::ExitCode::from(2)
        }
    }
}

fn run() -> Result<(), String> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [obj, softness, voxels @ ..] = args.as_slice() else {
        return Err("usage: mesh_field OBJ SOFTNESS [VOXEL...]".into());
    };
    let softness: f32 = softness.parse().map_err(|e| format!("softness: {e}"))?;
    let bytes = match obj.strip_prefix("icosphere:") {
        Some(levels) => hypertexture::mesh::displaced_icosphere_obj(
            levels.parse().map_err(|e| format!("levels: {e}"))?,
        )
        .into_bytes(),
        None => std::fs::read(obj).map_err(|e| format!("{obj}: {e}"))?,
    };
    let t = Instant::now();
    let mesh = Mesh::from_obj(obj, &bytes, Default::default()).map_err(|e| e.to_string())?;
    println!(
        "{obj}: {} triangles, loaded in {:.1} ms",
        mesh.triangle_count(),
        t.elapsed().as_secs_f64() * 1e3
    );
    let points = match std::env::var("POINTS") {
        Ok(n) => n.parse().map_err(|e| format!("POINTS={n}: {e}"))?,
        Err(_) => 200_000,
    };
    let voxels: Vec<f32> = if voxels.is_empty() {
        vec![softness / hypertexture::desc::FIELD_VOXELS_PER_SOFTNESS]
    } else {
        voxels
            .iter()
            .map(|v| v.parse().map_err(|e| format!("voxel: {e}")))
            .collect::<Result<_, _>>()?
    };
    for voxel in voxels {
        let spec = BandSpec {
            voxel,
            outer: softness,
            inner: 2.0 * voxel,
            max_bytes: DEFAULT_MAX_FIELD_BYTES * 8,
        };
        // The fastest of up to five builds, within about 5 s (the machine
        // is shared).
        let (start, mut runs) = (Instant::now(), 1);
        let t = Instant::now();
        let band = Band::build(&mesh, &spec)?;
        let mut build = t.elapsed().as_secs_f64() * 1e3;
        while runs < 5 && start.elapsed().as_secs_f64() < 5.0 {
            let t = Instant::now();
            Band::build(&mesh, &spec)?;
            build = build.min(t.elapsed().as_secs_f64() * 1e3);
            runs += 1;
        }
        let e = band.error(&mesh, softness, points, 1);
        println!(
            "voxel {voxel} (s/{:.1}): built in {build:.1} ms (fastest of {runs}), {} bricks, {:.1} MiB; |d - exact|/s max {:.4} rms {:.5}; |project - exact|/s max {:.4} rms {:.5}",
            softness / voxel,
            band.bricks(),
            band.memory_bytes() as f64 / 1048576.0,
            e.distance[0],
            e.distance[1],
            e.point[0],
            e.point[1]
        );
    }
    Ok(())
}
