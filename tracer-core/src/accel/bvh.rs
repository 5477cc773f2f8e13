use std::mem::MaybeUninit;

use glam::DVec3;

use crate::geometry::{Aabb, Ray};

/// One cache line holding **both children** of a binary BVH node, so a visit tests two boxes
/// from one memory fetch. Boxes are f32, rounded outward, which halves the footprint of f64
/// boxes; the slab test itself runs in f64 so that its precision matches the primitives'.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub struct Node {
    /// Per child: min x, min y, min z, max x, max y, max z.
    pub bounds: [[f32; 6]; 2],
    /// Per child: the child node's index, or a leaf's first primitive slot.
    pub index: [u32; 2],
    /// Per child: 0 for an interior child, else the leaf's primitive count.
    pub count: [u32; 2],
}

/// A BVH over primitives known only by their bounds; the owner intersects them through a
/// closure, so this module knows no geometry.
#[derive(Clone, Debug, Default)]
pub struct Bvh {
    pub nodes: Vec<Node>,
    /// `order[i]` is the original index of the primitive the owner must store at slot i.
    pub order: Vec<u32>,
    bounds: Option<Aabb>,
    depth: usize,
}

const BINS: usize = 16;
const MAX_LEAF: usize = 4;
const TRAVERSAL_COST: f64 = 1.0;
const INTERSECT_COST: f64 = 1.0;
const STACK_DEPTH: usize = 96;
/// Marks the missing second child of a root that is a single leaf.
const NO_CHILD: u32 = u32::MAX;
/// Subtrees at least this large are built on another rayon task.
const PARALLEL_THRESHOLD: usize = 4096;

/// The binary tree the builder makes before it is packed into [`Node`]s.
enum Tree {
    Leaf {
        bounds: Aabb,
        first: u32,
        count: u32,
    },
    Interior {
        bounds: Aabb,
        children: Box<[Tree; 2]>,
    },
}

impl Tree {
    fn bounds(&self) -> Aabb {
        match self {
            Tree::Leaf { bounds, .. } | Tree::Interior { bounds, .. } => *bounds,
        }
    }

    fn depth(&self) -> usize {
        match self {
            Tree::Leaf { .. } => 1,
            Tree::Interior { children, .. } => 1 + children[0].depth().max(children[1].depth()),
        }
    }
}

impl Bvh {
    /// Builds with the binned surface-area heuristic (16 bins on each axis), large subtrees
    /// in parallel. The result does not depend on the thread count.
    pub fn build(bounds: &[Aabb]) -> Bvh {
        let mut order: Vec<u32> = (0..bounds.len() as u32).collect();
        if bounds.is_empty() {
            return Bvh::default();
        }
        let centroids: Vec<DVec3> = bounds.iter().map(Aabb::centroid).collect();
        let builder = Builder {
            bounds,
            centroids: &centroids,
        };
        let tree = builder.build(&mut order, 0, 0);
        let mut nodes = Vec::with_capacity(bounds.len() / 2 + 1);
        let root_bounds = tree.bounds();
        let depth = tree.depth();
        match tree {
            Tree::Interior { children, .. } => {
                pack(&children, &mut nodes);
            }
            leaf @ Tree::Leaf { .. } => {
                // A lone leaf: one node whose second child is an empty box that nothing hits.
                let empty = Tree::Leaf {
                    bounds: Aabb::EMPTY,
                    first: 0,
                    count: 0,
                };
                pack(&[leaf, empty], &mut nodes);
                nodes[0].index[1] = NO_CHILD;
            }
        }
        Bvh {
            nodes,
            order,
            bounds: Some(root_bounds),
            depth,
        }
    }

    pub fn bounds(&self) -> Aabb {
        self.bounds.unwrap_or(Aabb::EMPTY)
    }

    pub fn depth(&self) -> usize {
        self.depth
    }

    /// Visits every leaf the ray may reach before `*t_max`, nearest child first. `leaf` gets
    /// a primitive range and shrinks `t_max` when it finds a closer hit; returning true stops
    /// the traversal (any-hit queries).
    #[inline(always)]
    pub fn traverse(
        &self,
        ray: &Ray,
        t_max: &mut f64,
        mut leaf: impl FnMut(std::ops::Range<usize>, &mut f64) -> bool,
    ) -> bool {
        if self.nodes.is_empty() {
            return false;
        }
        // Left uninitialised: zeroing 1.5 KB per query cost more than a whole traversal of a
        // ray that misses. Only slots below `top`, all written first, are ever read.
        let mut stack = [const { MaybeUninit::<(u32, f64)>::uninit() }; STACK_DEPTH];
        let mut top = 0;
        let mut index = 0usize;
        loop {
            let node = &self.nodes[index];
            let hit0 = slab(&node.bounds[0], ray, *t_max);
            let hit1 = slab(&node.bounds[1], ray, *t_max);
            let mut next: Option<usize> = None;
            // Nearer child first; leaves are intersected at once, since a hit shrinks t_max
            // and culls the rest.
            let order = if hit1 < hit0 { [1, 0] } else { [0, 1] };
            for c in order {
                let entry = if c == 0 { hit0 } else { hit1 };
                // A miss is +∞, which `> t_max` alone would let through when t_max is +∞.
                if entry == f64::INFINITY || entry > *t_max || node.index[c] == NO_CHILD {
                    continue;
                }
                let child = node.index[c] as usize;
                let count = node.count[c] as usize;
                if count > 0 {
                    if leaf(child..child + count, t_max) {
                        return true;
                    }
                } else if next.is_none() {
                    next = Some(child);
                } else {
                    stack[top].write((child as u32, entry));
                    top += 1;
                }
            }
            if let Some(n) = next {
                index = n;
                continue;
            }
            // Skip subtrees a hit found since they were pushed has put out of reach.
            loop {
                if top == 0 {
                    return false;
                }
                top -= 1;
                // SAFETY: slot `top` was written by the push that raised `top` above it.
                let (n, entry) = unsafe { stack[top].assume_init() };
                if entry <= *t_max {
                    index = n as usize;
                    break;
                }
            }
        }
    }
}

/// The slab test against an f32 box in f64: the entry distance, or +∞ on a miss.
#[inline(always)]
fn slab(b: &[f32; 6], ray: &Ray, t_max: f64) -> f64 {
    let tx0 = (b[0] as f64 - ray.origin.x) * ray.inv_dir.x;
    let tx1 = (b[3] as f64 - ray.origin.x) * ray.inv_dir.x;
    let ty0 = (b[1] as f64 - ray.origin.y) * ray.inv_dir.y;
    let ty1 = (b[4] as f64 - ray.origin.y) * ray.inv_dir.y;
    let tz0 = (b[2] as f64 - ray.origin.z) * ray.inv_dir.z;
    let tz1 = (b[5] as f64 - ray.origin.z) * ray.inv_dir.z;
    let near = tx0.min(tx1).max(ty0.min(ty1)).max(tz0.min(tz1)).max(0.0);
    let far = tx0.max(tx1).min(ty0.max(ty1)).min(tz0.max(tz1)).min(t_max);
    if near <= far {
        near
    } else {
        f64::INFINITY
    }
}

/// f32 box rounded outward, so it always contains the f64 box.
fn to_f32_box(b: Aabb) -> [f32; 6] {
    if b.is_empty() {
        return [
            f32::INFINITY,
            f32::INFINITY,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NEG_INFINITY,
            f32::NEG_INFINITY,
        ];
    }
    let b = b.padded();
    let down = |v: f64| {
        let f = v as f32;
        if (f as f64) > v {
            f.next_down()
        } else {
            f
        }
    };
    let up = |v: f64| {
        let f = v as f32;
        if (f as f64) < v {
            f.next_up()
        } else {
            f
        }
    };
    [
        down(b.min.x),
        down(b.min.y),
        down(b.min.z),
        up(b.max.x),
        up(b.max.y),
        up(b.max.z),
    ]
}

/// Appends the node holding `children` and, depth first, their subtrees; returns its index.
fn pack(children: &[Tree; 2], nodes: &mut Vec<Node>) -> u32 {
    let index = nodes.len();
    nodes.push(Node {
        bounds: [
            to_f32_box(children[0].bounds()),
            to_f32_box(children[1].bounds()),
        ],
        index: [0; 2],
        count: [0; 2],
    });
    for (c, child) in children.iter().enumerate() {
        let (child_index, count) = match child {
            Tree::Leaf { first, count, .. } => (*first, *count),
            Tree::Interior { children, .. } => (pack(children, nodes), 0),
        };
        nodes[index].index[c] = child_index;
        nodes[index].count[c] = count;
    }
    index as u32
}

struct Builder<'a> {
    bounds: &'a [Aabb],
    centroids: &'a [DVec3],
}

/// Primitives whose centroid falls in a bin below `bin` on `axis` go to the left child.
struct Split {
    axis: usize,
    lo: f64,
    scale: f64,
    bin: usize,
}

impl Split {
    fn goes_left(&self, centroid: f64) -> bool {
        bin_of(centroid, self.lo, self.scale) < self.bin
    }
}

impl Builder<'_> {
    fn build(&self, prims: &mut [u32], first: usize, depth: usize) -> Tree {
        let mut bounds = Aabb::EMPTY;
        let mut centroid_bounds = Aabb::EMPTY;
        for &p in prims.iter() {
            bounds = bounds.union(self.bounds[p as usize]);
            centroid_bounds = centroid_bounds.grow(self.centroids[p as usize]);
        }
        let leaf = Tree::Leaf {
            bounds,
            first: first as u32,
            count: prims.len() as u32,
        };
        // The depth cap keeps traversal's fixed stack from overflowing on adversarial input.
        if prims.len() <= 1 || depth + 2 >= STACK_DEPTH {
            return leaf;
        }
        let Some(split) = self.find_split(prims, bounds, centroid_bounds) else {
            return leaf;
        };
        let mid = partition(prims, |&p| {
            split.goes_left(self.centroids[p as usize][split.axis])
        });
        if mid == 0 || mid == prims.len() {
            return leaf;
        }
        let (left, right) = prims.split_at_mut(mid);
        let (l, r) = if prims_len(left, right) >= PARALLEL_THRESHOLD {
            rayon::join(
                || self.build(left, first, depth + 1),
                || self.build(right, first + mid, depth + 1),
            )
        } else {
            (
                self.build(left, first, depth + 1),
                self.build(right, first + mid, depth + 1),
            )
        };
        Tree::Interior {
            bounds,
            children: Box::new([l, r]),
        }
    }

    /// The cheapest binned SAH split over all three axes (binned in one pass), or None when
    /// a leaf is cheaper and small enough.
    fn find_split(&self, prims: &[u32], bounds: Aabb, centroid_bounds: Aabb) -> Option<Split> {
        let extent = centroid_bounds.extent();
        let lo = centroid_bounds.min;
        let scale = DVec3::new(
            if extent.x > 0.0 {
                BINS as f64 / extent.x
            } else {
                0.0
            },
            if extent.y > 0.0 {
                BINS as f64 / extent.y
            } else {
                0.0
            },
            if extent.z > 0.0 {
                BINS as f64 / extent.z
            } else {
                0.0
            },
        );
        let mut bin_bounds = [[Aabb::EMPTY; BINS]; 3];
        let mut bin_counts = [[0usize; BINS]; 3];
        for &p in prims {
            let c = self.centroids[p as usize];
            let b = self.bounds[p as usize];
            for axis in 0..3 {
                let bin = bin_of(c[axis], lo[axis], scale[axis]);
                bin_counts[axis][bin] += 1;
                bin_bounds[axis][bin] = bin_bounds[axis][bin].union(b);
            }
        }
        let mut best: Option<(f64, usize, usize)> = None;
        for axis in 0..3 {
            if extent[axis] <= 0.0 || extent[axis].is_nan() {
                continue;
            }
            let (boxes, counts) = (&bin_bounds[axis], &bin_counts[axis]);
            // Sweep from the right for each suffix's area and count, then from the left.
            let mut right_area = [0.0; BINS];
            let mut right_count = [0usize; BINS];
            let mut acc = Aabb::EMPTY;
            let mut count = 0;
            for i in (1..BINS).rev() {
                acc = acc.union(boxes[i]);
                count += counts[i];
                right_area[i] = acc.surface_area();
                right_count[i] = count;
            }
            let mut acc = Aabb::EMPTY;
            let mut count = 0;
            for split in 1..BINS {
                acc = acc.union(boxes[split - 1]);
                count += counts[split - 1];
                if count == 0 || right_count[split] == 0 {
                    continue;
                }
                let cost = acc.surface_area() * count as f64
                    + right_area[split] * right_count[split] as f64;
                if best.is_none_or(|(c, _, _)| cost < c) {
                    best = Some((cost, axis, split));
                }
            }
        }
        let (cost, axis, bin) = best?;
        let split_cost =
            TRAVERSAL_COST + INTERSECT_COST * cost / bounds.surface_area().max(f64::MIN_POSITIVE);
        let leaf_cost = INTERSECT_COST * prims.len() as f64;
        if prims.len() <= MAX_LEAF && leaf_cost <= split_cost {
            return None;
        }
        Some(Split {
            axis,
            lo: lo[axis],
            scale: scale[axis],
            bin,
        })
    }
}

fn prims_len(a: &[u32], b: &[u32]) -> usize {
    a.len().min(b.len())
}

#[inline]
fn bin_of(c: f64, lo: f64, scale: f64) -> usize {
    (((c - lo) * scale) as usize).min(BINS - 1)
}

/// In-place partition; returns the number of elements for which `left` holds.
fn partition(items: &mut [u32], left: impl Fn(&u32) -> bool) -> usize {
    let mut i = 0;
    for j in 0..items.len() {
        if left(&items[j]) {
            items.swap(i, j);
            i += 1;
        }
    }
    i
}

#[cfg(test)]
mod tests {
    use super::*;

    fn boxes(n: usize) -> Vec<Aabb> {
        // A deterministic scatter of small boxes.
        let mut state = 12345u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        (0..n)
            .map(|_| {
                let c = DVec3::new(next(), next(), next()) * 100.0;
                let e = DVec3::new(next(), next(), next());
                Aabb {
                    min: c - e,
                    max: c + e,
                }
            })
            .collect()
    }

    fn leaves(bvh: &Bvh) -> Vec<([f32; 6], u32, u32)> {
        bvh.nodes
            .iter()
            .flat_map(|n| (0..2).map(move |c| (n.bounds[c], n.index[c], n.count[c])))
            .filter(|(_, _, count)| *count > 0)
            .collect()
    }

    #[test]
    fn every_primitive_sits_in_exactly_one_leaf_inside_its_bounds() {
        let prims = boxes(5000);
        let bvh = Bvh::build(&prims);
        let mut seen = vec![0; prims.len()];
        for (b, first, count) in leaves(&bvh) {
            for slot in first..first + count {
                let p = bvh.order[slot as usize] as usize;
                seen[p] += 1;
                let pb = prims[p];
                let inside = (b[0] as f64) <= pb.min.x
                    && (b[1] as f64) <= pb.min.y
                    && (b[2] as f64) <= pb.min.z
                    && (b[3] as f64) >= pb.max.x
                    && (b[4] as f64) >= pb.max.y
                    && (b[5] as f64) >= pb.max.z;
                assert!(inside);
            }
        }
        assert!(seen.iter().all(|&s| s == 1));
        assert!(bvh.depth() < 40, "depth {}", bvh.depth());
    }

    #[test]
    fn traversal_finds_the_same_boxes_as_brute_force() {
        let prims = boxes(2000);
        let bvh = Bvh::build(&prims);
        for i in 0..200 {
            let origin = DVec3::new(-10.0, i as f64 * 0.5, 50.0);
            let ray = Ray::new(origin, DVec3::new(1.0, 0.01 * i as f64, -0.3).normalize());
            let mut expected: Vec<usize> = (0..prims.len())
                .filter(|&p| prims[p].hit(&ray, f64::INFINITY).is_some())
                .collect();
            let mut found = Vec::new();
            let mut t_max = f64::INFINITY;
            bvh.traverse(&ray, &mut t_max, |range, _| {
                for slot in range {
                    let p = bvh.order[slot] as usize;
                    if prims[p].hit(&ray, f64::INFINITY).is_some() {
                        found.push(p);
                    }
                }
                false
            });
            expected.sort();
            found.sort();
            assert_eq!(found, expected);
        }
    }

    #[test]
    fn a_single_primitive_and_identical_centroids_make_one_leaf() {
        let b = Aabb {
            min: DVec3::ZERO,
            max: DVec3::ONE,
        };
        for n in [1, 100] {
            let bvh = Bvh::build(&vec![b; n]);
            assert_eq!(bvh.nodes.len(), 1);
            assert_eq!(leaves(&bvh)[0], (to_f32_box(b), 0, n as u32));
            let ray = Ray::new(DVec3::new(0.5, 0.5, 5.0), -DVec3::Z);
            let mut visited = 0;
            bvh.traverse(&ray, &mut f64::INFINITY.clone(), |r, _| {
                visited += r.len();
                false
            });
            assert_eq!(visited, n);
        }
    }

    #[test]
    fn build_is_the_same_on_any_thread_count() {
        let prims = boxes(20_000);
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let a = one.install(|| Bvh::build(&prims));
        let b = Bvh::build(&prims);
        assert_eq!(a.order, b.order);
        assert_eq!(a.nodes.len(), b.nodes.len());
    }

    #[test]
    fn f32_boxes_contain_their_f64_boxes() {
        let b = Aabb {
            min: DVec3::new(0.1, -1e5 - 0.001, 1e-7),
            max: DVec3::new(0.3, 1e30, 1e-7),
        };
        let f = to_f32_box(b);
        assert!((f[0] as f64) <= 0.1 && (f[1] as f64) <= -1e5 - 0.001 && (f[2] as f64) <= 1e-7);
        assert!((f[3] as f64) >= 0.3 && (f[4] as f64) >= 1e30 && (f[5] as f64) >= 1e-7);
    }
}
