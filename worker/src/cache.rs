//! The meshes a worker keeps between assignments: the least recently used
//! go first, so the cache holds at most its budget of bytes (`worker
//! --asset-cache-mb`) whatever a coordinator sends.

use std::collections::HashMap;
use std::sync::Arc;

use hypertexture::mesh::Mesh;

/// The default budget of `--asset-cache-mb`.
pub const DEFAULT_ASSET_CACHE_MB: u64 = 512;

/// Meshes by content hash, within a budget of bytes ([`Mesh::memory_bytes`]).
pub struct AssetCache {
    entries: HashMap<u64, Entry>,
    /// The bytes of every entry.
    bytes: u64,
    /// The most bytes kept, but for the meshes of the scene in use.
    budget: u64,
    /// Counts uses: an entry's `used` is the count at its last use.
    clock: u64,
}

struct Entry {
    mesh: Arc<Mesh>,
    bytes: u64,
    used: u64,
}

impl AssetCache {
    /// An empty cache that keeps at most `budget` bytes.
    pub fn new(budget: u64) -> AssetCache {
        AssetCache {
            entries: HashMap::new(),
            bytes: 0,
            budget,
            clock: 0,
        }
    }

    /// Whether the mesh of this hash is kept.
    pub fn contains(&self, hash: u64) -> bool {
        self.entries.contains_key(&hash)
    }

    /// The mesh of this hash, now the most recently used.
    pub fn get(&mut self, hash: u64) -> Option<Arc<Mesh>> {
        self.clock += 1;
        let entry = self.entries.get_mut(&hash)?;
        entry.used = self.clock;
        Some(Arc::clone(&entry.mesh))
    }

    /// The bytes kept.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// How many meshes are kept.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether none is kept.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Keeps `mesh` as the most recently used, then drops the least recently
    /// used meshes, other than those in `pinned` (the scene in use), until
    /// the cache is within its budget. Returns the hashes dropped.
    pub fn keep(&mut self, hash: u64, mesh: Arc<Mesh>, pinned: &[u64]) -> Vec<u64> {
        self.clock += 1;
        let used = self.clock;
        match self.entries.get_mut(&hash) {
            Some(entry) => entry.used = used,
            None => {
                let bytes = mesh.memory_bytes() as u64;
                self.bytes += bytes;
                self.entries.insert(hash, Entry { mesh, bytes, used });
            }
        }
        let mut dropped = Vec::new();
        while self.bytes > self.budget {
            let oldest = self
                .entries
                .iter()
                .filter(|(h, _)| !pinned.contains(h))
                .min_by_key(|(_, e)| e.used)
                .map(|(h, _)| *h);
            let Some(oldest) = oldest else { break };
            if let Some(entry) = self.entries.remove(&oldest) {
                self.bytes -= entry.bytes;
            }
            dropped.push(oldest);
        }
        dropped
    }
}

/// The OBJ text of a closed tetrahedron whose first corner is moved by `k`
/// (a distinct file, so a distinct hash, for each k).
#[cfg(test)]
pub(crate) fn tetrahedron_obj(k: u32) -> String {
    format!(
        "v {} 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n",
        -(k as f32) * 0.001
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tetrahedron(k: u32) -> Arc<Mesh> {
        let obj = tetrahedron_obj(k);
        Arc::new(Mesh::from_obj("t.obj", obj.as_bytes(), Default::default()).unwrap())
    }

    #[test]
    fn the_least_recently_used_go_first_and_the_budget_holds() {
        let one = tetrahedron(0).memory_bytes() as u64;
        let mut cache = AssetCache::new(3 * one);
        for k in 0..3 {
            assert!(cache.keep(k.into(), tetrahedron(k), &[]).is_empty());
        }
        assert_eq!(cache.len(), 3);
        // 0 is used again: 1 is now the oldest.
        assert!(cache.get(0).is_some());
        assert_eq!(cache.keep(3, tetrahedron(3), &[]), [1]);
        assert!(cache.contains(0) && !cache.contains(1));
        assert!(cache.bytes() <= 3 * one);
        // A thousand more: still three.
        for k in 4..1004 {
            cache.keep(k.into(), tetrahedron(k), &[]);
            assert!(cache.bytes() <= 3 * one);
        }
        assert_eq!(cache.len(), 3);
    }

    #[test]
    fn the_scene_in_use_keeps_its_meshes_over_the_budget() {
        let mut cache = AssetCache::new(0);
        assert!(cache.keep(1, tetrahedron(1), &[1, 2]).is_empty());
        assert!(cache.keep(2, tetrahedron(2), &[1, 2]).is_empty());
        assert_eq!(cache.len(), 2);
        // The next scene's mesh comes in: the others go.
        let mut dropped = cache.keep(3, tetrahedron(3), &[3]);
        dropped.sort_unstable();
        assert_eq!(dropped, [1, 2]);
        assert_eq!(cache.len(), 1);
        assert!(cache.keep(4, tetrahedron(4), &[]).contains(&3));
        assert!(cache.is_empty() && cache.bytes() == 0);
    }
}
