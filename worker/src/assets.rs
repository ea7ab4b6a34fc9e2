//! The files a scene names (meshes), fetched from the coordinator when this
//! worker does not hold them, checked and built off the async thread.

use std::sync::Arc;

use hypertexture_proto::{FailureKind, pb};

use crate::connection::{Client, shown};
use crate::{Fetched, SceneCache};

/// Fetches the files an assignment's scene names that this worker does not
/// hold (`GetAsset`), checks each against its size and hash, and builds its
/// mesh off the async thread. They are the caller's to hand to
/// [`SceneCache::get`], which keeps them once the scene's hash has matched.
/// A file that does not arrive whole and intact fails the assignment; one
/// that arrives but is not a usable mesh fails the scene.
pub(crate) async fn fetch_assets(
    client: &mut Client,
    worker_id: &str,
    scenes: &SceneCache,
    assignment: &pb::Assignment,
) -> Result<Fetched, (FailureKind, String)> {
    let mut fetched = Fetched::new();
    let Some(job) = &assignment.job else {
        return Ok(fetched);
    };
    for a in scenes.missing(job) {
        let failed = |e: String| {
            (
                FailureKind::Assignment,
                format!("{}: fetching {}: {e}", job.scene_name, a.path),
            )
        };
        if a.size > hypertexture::mesh::MAX_OBJ_BYTES {
            return Err(failed(format!(
                "{} bytes is more than a mesh file may be",
                a.size
            )));
        }
        let started = std::time::Instant::now();
        let mut stream = client
            .get_asset(pb::GetAssetParams {
                worker_id: worker_id.to_string(),
                hash: a.hash,
            })
            .await
            .map_err(|s| failed(s.message().to_string()))?
            .into_inner();
        let mut bytes = Vec::with_capacity(a.size as usize);
        while let Some(chunk) = stream
            .message()
            .await
            .map_err(|s| failed(s.message().to_string()))?
        {
            if bytes.len() as u64 + chunk.chunk.len() as u64 > a.size {
                return Err(failed(format!("more than the {} bytes announced", a.size)));
            }
            bytes.extend_from_slice(&chunk.chunk);
        }
        let got = hypertexture::mesh::content_hash(&bytes);
        if bytes.len() as u64 != a.size || got != a.hash {
            return Err(failed(format!(
                "{} bytes with hash {got:016x} arrived, not {} with hash {:016x}",
                bytes.len(),
                a.size,
                a.hash
            )));
        }
        let fetched_in = started.elapsed();
        let path = a.path.clone();
        let mesh = tokio::task::spawn_blocking(move || {
            hypertexture::mesh::Mesh::from_obj(&path, &bytes, Default::default())
        })
        .await
        .map_err(|e| failed(format!("the mesh build stopped: {e}")))?
        .map_err(|e| (FailureKind::Scene, format!("{}: {e}", job.scene_name)))?;
        tracing::info!(
            "{}: {} ({} bytes, {} triangles) fetched in {:.1} ms, its distance tree built in {:.1} ms",
            shown(&job.scene_name),
            shown(&a.path),
            a.size,
            mesh.triangle_count(),
            fetched_in.as_secs_f64() * 1e3,
            (started.elapsed() - fetched_in).as_secs_f64() * 1e3
        );
        fetched.insert(a.hash, Arc::new(mesh));
    }
    Ok(fetched)
}
