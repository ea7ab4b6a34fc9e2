//! A bounding volume hierarchy over triangles for closest-point queries.
//!
//! Built top-down by splitting each node's triangles at the median of their
//! centroids along the longest axis of the centroids' box (ties broken by the
//! triangle's index, so the tree is a function of the triangles alone), down
//! to leaves of at most [`LEAF`] triangles.

use glam::Vec3;

/// The most triangles in a leaf.
const LEAF: usize = 4;

/// The deepest tree a query's stack holds (a median split halves the
/// triangles at each level: 2⁴⁸ leaves is far beyond any triangle cap).
const MAX_DEPTH: usize = 64;

/// One node: a box, and either two children (`count == 0`: at `first` and
/// `first + 1`) or a leaf's triangles `first .. first + count`.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Node {
    min: Vec3,
    max: Vec3,
    first: u32,
    count: u32,
}

/// What a node holds.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(super) enum Content {
    /// The indices of its two children.
    Inner(usize, usize),
    /// The triangles of a leaf.
    Leaf(std::ops::Range<usize>),
}

/// The tree (nodes in a flat array, the root first).
#[derive(Clone, Debug, PartialEq)]
pub(super) struct Bvh {
    nodes: Vec<Node>,
}

impl Bvh {
    /// The bytes of its nodes.
    pub(super) fn memory_bytes(&self) -> usize {
        self.nodes.capacity() * std::mem::size_of::<Node>()
    }

    /// The tree over `triangles` and the order the leaves take them in (the
    /// caller stores the triangles in that order).
    pub(super) fn build(triangles: &[[Vec3; 3]]) -> (Bvh, Vec<u32>) {
        let mut order: Vec<u32> = (0..triangles.len() as u32).collect();
        let centroids: Vec<Vec3> = triangles
            .iter()
            .map(|t| (t[0] + t[1] + t[2]) * (1.0 / 3.0))
            .collect();
        let mut nodes = vec![Node {
            min: Vec3::ZERO,
            max: Vec3::ZERO,
            first: 0,
            count: 0,
        }];
        // (node, range of `order`): nodes still to fill in.
        let mut pending = vec![(0usize, 0usize, order.len())];
        while let Some((node, lo, hi)) = pending.pop() {
            let items = &mut order[lo..hi];
            let (min, max) =
                items
                    .iter()
                    .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), &i| {
                        let t = &triangles[i as usize];
                        (
                            lo.min(t[0]).min(t[1]).min(t[2]),
                            hi.max(t[0]).max(t[1]).max(t[2]),
                        )
                    });
            if items.len() <= LEAF {
                nodes[node] = Node {
                    min,
                    max,
                    first: lo as u32,
                    count: items.len() as u32,
                };
                continue;
            }
            let (cmin, cmax) = items
                .iter()
                .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), &i| {
                    (lo.min(centroids[i as usize]), hi.max(centroids[i as usize]))
                });
            let extent = cmax - cmin;
            let axis = if extent.x >= extent.y && extent.x >= extent.z {
                0
            } else if extent.y >= extent.z {
                1
            } else {
                2
            };
            let mid = items.len() / 2;
            items.select_nth_unstable_by(mid, |&a, &b| {
                centroids[a as usize][axis]
                    .total_cmp(&centroids[b as usize][axis])
                    .then(a.cmp(&b))
            });
            let left = nodes.len();
            nodes.push(nodes[node]);
            nodes.push(nodes[node]);
            nodes[node] = Node {
                min,
                max,
                first: left as u32,
                count: 0,
            };
            pending.push((left + 1, lo + mid, hi));
            pending.push((left, lo, lo + mid));
        }
        (Bvh { nodes }, order)
    }

    /// The number of nodes; a node's children come after it, so going down
    /// the indices visits every child before its parent.
    pub(super) fn len(&self) -> usize {
        self.nodes.len()
    }

    /// The box (min, max) of node `i`.
    pub(super) fn bounds(&self, i: usize) -> (Vec3, Vec3) {
        (self.nodes[i].min, self.nodes[i].max)
    }

    /// What node `i` holds: two children, or a leaf's triangles (indices in
    /// the order the tree stores them).
    #[inline]
    pub(super) fn content(&self, i: usize) -> Content {
        let n = &self.nodes[i];
        if n.count > 0 {
            Content::Leaf(n.first as usize..(n.first + n.count) as usize)
        } else {
            Content::Inner(n.first as usize, n.first as usize + 1)
        }
    }

    /// Calls `test` on the index of every triangle that may be closer to `p`
    /// than the best so far, nearer boxes first; `test` returns the best
    /// squared distance after the triangle (∞ before any).
    #[inline]
    pub(super) fn visit(&self, p: Vec3, mut test: impl FnMut(usize) -> f32) {
        let mut best = f32::INFINITY;
        let mut stack = [0u32; MAX_DEPTH];
        let mut top = 1;
        while top > 0 {
            top -= 1;
            let node = &self.nodes[stack[top] as usize];
            if box_distance2(p, node) >= best {
                continue;
            }
            if node.count > 0 {
                for i in node.first..node.first + node.count {
                    best = test(i as usize);
                }
                continue;
            }
            let (a, b) = (node.first, node.first + 1);
            let da = box_distance2(p, &self.nodes[a as usize]);
            let db = box_distance2(p, &self.nodes[b as usize]);
            // The nearer child goes on top and is searched first.
            let (near, far) = if db < da { (b, a) } else { (a, b) };
            stack[top] = far;
            stack[top + 1] = near;
            top += 2;
        }
    }
}

/// The squared distance from `p` to a node's box (0 inside).
#[inline(always)]
fn box_distance2(p: Vec3, node: &Node) -> f32 {
    let d = (node.min - p).max(p - node.max).max(Vec3::ZERO);
    d.length_squared()
}
