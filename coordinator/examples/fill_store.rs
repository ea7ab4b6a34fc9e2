//! Fills a service's store with jobs part-rendered, to measure a restart:
//! `fill_store DIR UNITS` stores jobs of `scenes/noisy_sphere.ron` at 512×512
//! (64 units a frame), each with 63 of its 64 units stored, until UNITS units
//! are stored. Then `coordinator serve --data DIR --local-workers 0` resumes
//! them all; its log says how long that took.

use coordinator::service::jobs::JobSpec;
use coordinator::service::store::Store;
use hypertexture::render::interleave::farm_units;
use hypertexture::{Overrides, PixelFormat, RenderRequest};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let (Some(dir), Some(units)) = (args.next(), args.next()) else {
        eprintln!("usage: fill_store DIR UNITS");
        std::process::exit(2);
    };
    let units: usize = units.parse()?;
    let out = std::env::temp_dir().join("hypertexture-fill-store");
    std::fs::create_dir_all(&out)?;
    let store = Store::open(std::path::Path::new(&dir))?;
    let scene = std::fs::read_to_string("scenes/noisy_sphere.ron")?;
    let layout = farm_units(512, 512, 8, 64);
    let per_job = layout.len() - 1;
    let mut stored = 0;
    let mut job = 0;
    while stored < units {
        let spec = JobSpec {
            request: RenderRequest {
                overrides: Overrides {
                    width: Some(512),
                    height: Some(512),
                    ..Overrides::default()
                },
                pixel_format: PixelFormat::Srgb8,
                ..RenderRequest::new(scene.clone(), "noisy_sphere.ron")
            },
            out: out.join(format!("job{job}.png")).display().to_string(),
            priority: 0,
            require_tags: Vec::new(),
        };
        let json = coordinator::service::stored_spec_json(&spec, 8, 64)?;
        let id = store.insert_job(&json, 0, 0)?;
        for (u, unit) in layout.iter().enumerate().take(per_job.min(units - stored)) {
            let tile = vec![0x80u8; unit.pixel_count(512) * 4];
            store.put_tile(id, 0, u as u32, &tile)?;
            stored += 1;
        }
        job += 1;
    }
    println!("{job} jobs, {stored} units stored in {dir}");
    Ok(())
}
