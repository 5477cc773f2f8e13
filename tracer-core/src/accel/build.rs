//! Building a [`Bvh`]: binned SAH over the primitives' bounds (rounded outward to f32, binned
//! with f32 SIMD min/max, the references partitioned in place), large subtrees in parallel,
//! then the binary tree collapsed into `WIDTH`-wide nodes with outward-rounded f32 boxes.

use glam::DVec3;
use rayon::prelude::*;

use super::bvh::{round_down, round_up, Bvh, Node, MAX_DEPTH, NO_CHILD, WIDTH};
use super::memory::with_capacity_huge;
use crate::geometry::Aabb;

const BINS: usize = 16;
const MAX_LEAF: usize = 4;
/// With primitives in blocks, a leaf may hold this many blocks when the SAH finds that
/// cheaper than splitting: a second block in a leaf costs less than the node visit a split
/// adds (fewer, shallower nodes; 10% more incoherent rays per second on dragon).
const MAX_LEAF_BLOCKS: usize = 2;
const TRAVERSAL_COST: f64 = 1.0;
const INTERSECT_COST: f64 = 1.0;
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
    /// in parallel, then collapses the binary tree into `WIDTH`-wide nodes. The result does not
    /// depend on the thread count.
    pub fn build(bounds: &[Aabb]) -> Bvh {
        Bvh::build_aligned(bounds, 1)
    }

    /// Like [`Bvh::build`], with every leaf's first slot a multiple of `align`: `order` is
    /// padded with [`PADDING`] slots, so that an owner can keep its primitives in blocks of
    /// `align` with no leaf straddling two blocks it does not need.
    pub fn build_aligned(bounds: &[Aabb], align: usize) -> Bvh {
        if bounds.is_empty() {
            return Bvh::default();
        }
        assert!(bounds.len() < MAX_PRIMS, "too many primitives for one BVH");
        let mut refs = Vec::with_capacity(bounds.len());
        bounds
            .par_iter()
            .enumerate()
            .map(|(i, b)| PrimRef::of(b, i as u32))
            .collect_into_vec(&mut refs);
        let (root_bounds, root_centroids) = bounds
            .par_iter()
            .zip(&refs)
            .fold(
                || (Aabb::EMPTY, Box4::EMPTY),
                |(b, mut c), (pb, r)| {
                    c.grow_point(&r.0.centroid2());
                    (b.union(*pb), c)
                },
            )
            .reduce(
                || (Aabb::EMPTY, Box4::EMPTY),
                |(b0, mut c0), (b1, c1)| {
                    c0.grow(&c1);
                    (b0.union(b1), c0)
                },
            );
        let builder = Builder {
            align,
            align_shift: align.is_power_of_two().then(|| align.trailing_zeros()),
        };
        let mut tree = builder.build(&mut refs, 0, 0, root_bounds, root_centroids);
        let mut order = Vec::with_capacity(refs.len());
        refs.par_iter()
            .map(PrimRef::id)
            .collect_into_vec(&mut order);
        drop(refs);
        if align > 1 {
            let mut aligned = Vec::with_capacity(order.len() + order.len() / 2);
            align_leaves(&mut tree, &order, align, &mut aligned);
            order = aligned;
        }
        let mut nodes = with_capacity_huge(bounds.len() / 4 + 1);
        let root_bounds = tree.bounds();
        let depth = tree.depth();
        match &tree {
            Tree::Interior { children, .. } => {
                pack(children, &mut nodes);
            }
            leaf @ Tree::Leaf { .. } => {
                // A lone leaf: one node with one used slot.
                pack_node(&[leaf], &mut nodes);
            }
        }
        Bvh {
            nodes,
            order,
            bounds: Some(root_bounds),
            depth,
        }
    }
}

/// Marks a padding slot in the `order` of [`Bvh::build_aligned`].
pub const PADDING: u32 = u32::MAX;

/// Copies the leaves' primitives from `order` to `out` in leaf order, each leaf starting on a
/// multiple of `align` (gaps filled with [`PADDING`]), and points the leaves at their new slots.
fn align_leaves(tree: &mut Tree, order: &[u32], align: usize, out: &mut Vec<u32>) {
    match tree {
        Tree::Leaf { first, count, .. } => {
            let start = out.len();
            out.extend_from_slice(&order[*first as usize..(*first + *count) as usize]);
            out.resize(out.len().next_multiple_of(align), PADDING);
            *first = start as u32;
        }
        Tree::Interior { children, .. } => {
            for child in children.iter_mut() {
                align_leaves(child, order, align, out);
            }
        }
    }
}

/// f32 box rounded outward, so it always contains the f64 box.
pub(super) fn to_f32_box(b: Aabb) -> [f32; 6] {
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
    [
        round_down(b.min.x),
        round_down(b.min.y),
        round_down(b.min.z),
        round_up(b.max.x),
        round_up(b.max.y),
        round_up(b.max.z),
    ]
}

/// Appends the wide node that replaces the binary node with `children`: the binary tree is
/// opened below it, largest interior child first, until it has `WIDTH` children. Subtrees follow
/// depth first; returns the node's index.
fn pack(children: &[Tree; 2], nodes: &mut Vec<Node>) -> u32 {
    let mut slots: Vec<&Tree> = Vec::with_capacity(WIDTH);
    slots.extend([&children[0], &children[1]]);
    while slots.len() < WIDTH {
        let widest = slots
            .iter()
            .enumerate()
            .filter(|(_, t)| matches!(t, Tree::Interior { .. }))
            .max_by(|(_, a), (_, b)| {
                a.bounds()
                    .surface_area()
                    .total_cmp(&b.bounds().surface_area())
            })
            .map(|(i, _)| i);
        let Some(i) = widest else { break };
        let Tree::Interior { children, .. } = slots[i] else {
            unreachable!()
        };
        slots[i] = &children[0];
        slots.insert(i + 1, &children[1]);
    }
    pack_node(&slots, nodes)
}

fn pack_node(slots: &[&Tree], nodes: &mut Vec<Node>) -> u32 {
    let index = nodes.len();
    let mut node = Node {
        bounds: [
            [f32::INFINITY; WIDTH],
            [f32::NEG_INFINITY; WIDTH],
            [f32::INFINITY; WIDTH],
            [f32::NEG_INFINITY; WIDTH],
            [f32::INFINITY; WIDTH],
            [f32::NEG_INFINITY; WIDTH],
        ],
        index: [NO_CHILD; WIDTH],
        count: [0; WIDTH],
    };
    for (c, child) in slots.iter().enumerate() {
        let b = to_f32_box(child.bounds());
        for a in 0..3 {
            node.bounds[2 * a][c] = b[a];
            node.bounds[2 * a + 1][c] = b[a + 3];
        }
    }
    nodes.push(node);
    for (c, child) in slots.iter().enumerate() {
        let (child_index, count) = match child {
            Tree::Leaf { first, count, .. } => (*first, *count),
            Tree::Interior { children, .. } => (pack(children, nodes), 0),
        };
        nodes[index].index[c] = child_index;
        nodes[index].count[c] = count;
    }
    index as u32
}

struct Builder {
    /// The owner tests primitives in blocks of this many at the cost of one.
    align: usize,
    /// log2(`align`) where `align` is a power of two.
    align_shift: Option<u32>,
}

/// Primitives whose centroid falls in a bin below `bin` on `axis` go to the left child.
struct Split {
    axis: usize,
    lo: [f32; 4],
    scale: [f32; 4],
    bins: usize,
    bin: usize,
    /// The children's bounds, from the bins.
    left: Aabb,
    right: Aabb,
}

impl Split {
    #[inline(always)]
    fn goes_left(&self, centroid2: &[f32; 4]) -> bool {
        Box4::bins_of(centroid2, &self.lo, &self.scale, (self.bins - 1) as f32)[self.axis]
            < self.bin as u32
    }
}

/// A box in f32 as four lanes of minima and four of maxima (the fourth lane unused): a
/// primitive's bounds rounded outward, a bin, or the bounds of centroids. Growing one is a
/// SIMD min and max; in f64 (eight lanes, twice the bytes) binning cost half again as much.
#[derive(Clone, Copy)]
#[repr(C, align(32))]
struct Box4 {
    lo: [f32; 4],
    hi: [f32; 4],
}

/// A primitive's bounds rounded outward to f32 (they contain the f64 bounds, so every box
/// made from them holds its primitives), and its index in the unused lane. The builder
/// partitions these themselves, not indices into them, so binning reads them in order
/// instead of one cache miss per primitive. Centroids are worked out from them where needed
/// (an array of them cost bytes per primitive and the kernel's time to hand out pages).
#[derive(Clone, Copy)]
struct PrimRef(Box4);

/// Indices are kept as normal f32 bit patterns (offset by the smallest normal's bits), so
/// that no arithmetic on the unused lane meets a subnormal, which can be slow.
const ID_BIAS: u32 = 0x0080_0000;
/// The most primitives a BVH takes: indices stay below the bits of infinity.
const MAX_PRIMS: usize = (0x7F80_0000 - ID_BIAS) as usize;

impl PrimRef {
    fn of(b: &Aabb, id: u32) -> PrimRef {
        let mut r = Box4::of(b);
        r.lo[3] = f32::from_bits(id + ID_BIAS);
        PrimRef(r)
    }

    fn id(&self) -> u32 {
        self.0.lo[3].to_bits() - ID_BIAS
    }
}

impl Box4 {
    const EMPTY: Box4 = Box4 {
        lo: [f32::INFINITY; 4],
        hi: [f32::NEG_INFINITY; 4],
    };

    fn of(b: &Aabb) -> Box4 {
        Box4 {
            lo: [
                round_down(b.min.x),
                round_down(b.min.y),
                round_down(b.min.z),
                0.0,
            ],
            hi: [round_up(b.max.x), round_up(b.max.y), round_up(b.max.z), 0.0],
        }
    }

    /// Twice the centroid (the bins' scale takes the half); the same f32 values wherever
    /// they are worked out, so binning and partitioning agree.
    /// The fourth lane is 0: in a [`PrimRef`] it holds an index, and differences of those
    /// bit patterns would be subnormal (a slow path on the CPU).
    #[inline(always)]
    fn centroid2(&self) -> [f32; 4] {
        std::array::from_fn(|k| if k < 3 { self.lo[k] + self.hi[k] } else { 0.0 })
    }

    /// The bins of a doubled centroid on each axis (the fourth lane unused): truncated and
    /// clamped to `0..=last`, NaN to 0.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn bins_of(c: &[f32; 4], lo: &[f32; 4], scale: &[f32; 4], last: f32) -> [u32; 4] {
        use std::arch::x86_64::*;
        // SAFETY: SSE2 is part of the x86_64 baseline; the loads and the store move four
        // f32s or i32s of arrays of four.
        unsafe {
            let x = _mm_mul_ps(
                _mm_sub_ps(_mm_loadu_ps(c.as_ptr()), _mm_loadu_ps(lo.as_ptr())),
                _mm_loadu_ps(scale.as_ptr()),
            );
            // Lane for lane the portable version's selects: `max` gives 0 for NaN (its
            // second operand), `min` keeps `x` only when below `last`.
            let x = _mm_min_ps(_mm_max_ps(x, _mm_setzero_ps()), _mm_set1_ps(last));
            let mut out = [0u32; 4];
            _mm_storeu_si128(out.as_mut_ptr().cast(), _mm_cvttps_epi32(x));
            out
        }
    }

    #[cfg(not(target_arch = "x86_64"))]
    #[inline(always)]
    fn bins_of(c: &[f32; 4], lo: &[f32; 4], scale: &[f32; 4], last: f32) -> [u32; 4] {
        std::array::from_fn(|k| {
            let x = (c[k] - lo[k]) * scale[k];
            // `x > 0` is false for NaN.
            let x = if x > 0.0 { x } else { 0.0 };
            let x = if x < last { x } else { last };
            // SAFETY: `x` is finite and within 0..=last (at most 15): no conversion
            // overflows. (`as` would add a saturating check per lane.)
            unsafe { x.to_int_unchecked::<i32>() as u32 }
        })
    }

    /// `self` grown by `b`. A NaN in `b` leaves `self` as it was (as `f64::min` did).
    #[inline(always)]
    fn grow(&mut self, b: &Box4) {
        for k in 0..4 {
            self.lo[k] = if b.lo[k] < self.lo[k] {
                b.lo[k]
            } else {
                self.lo[k]
            };
            self.hi[k] = if b.hi[k] > self.hi[k] {
                b.hi[k]
            } else {
                self.hi[k]
            };
        }
    }

    #[inline(always)]
    fn grow_point(&mut self, p: &[f32; 4]) {
        self.grow(&Box4 { lo: *p, hi: *p });
    }

    /// Surface area of a non-empty box (the sweeps only measure boxes holding primitives).
    #[inline(always)]
    fn area(&self) -> f64 {
        let (x, y, z) = (
            self.hi[0] - self.lo[0],
            self.hi[1] - self.lo[1],
            self.hi[2] - self.lo[2],
        );
        (2.0 * (x * y + y * z + z * x)) as f64
    }

    fn aabb(&self) -> Aabb {
        Aabb {
            min: DVec3::new(self.lo[0] as f64, self.lo[1] as f64, self.lo[2] as f64),
            max: DVec3::new(self.hi[0] as f64, self.hi[1] as f64, self.hi[2] as f64),
        }
    }
}

/// Per axis and bin: the union of the primitives' bounds and their number.
#[derive(Clone)]
struct Bins {
    bounds: [[Box4; BINS]; 3],
    counts: [[u32; BINS]; 3],
}

impl Bins {
    fn empty() -> Bins {
        Bins {
            bounds: [[Box4::EMPTY; BINS]; 3],
            counts: [[0; BINS]; 3],
        }
    }

    /// Exact (min, max and integer sums), so any grouping of the merges gives the same bins.
    fn merge(mut self, o: Bins) -> Bins {
        for axis in 0..3 {
            for bin in 0..BINS {
                self.bounds[axis][bin].grow(&o.bounds[axis][bin]);
                self.counts[axis][bin] += o.counts[axis][bin];
            }
        }
        self
    }
}

/// Nodes at least this large bin their primitives in parallel chunks.
const PARALLEL_BINNING: usize = 16 * 1024;

impl Builder {
    /// `bounds` and `centroid_bounds` are those of `prims`, found by the caller.
    fn build(
        &self,
        prims: &mut [PrimRef],
        first: usize,
        depth: usize,
        bounds: Aabb,
        centroid_bounds: Box4,
    ) -> Tree {
        let leaf = Tree::Leaf {
            bounds,
            first: first as u32,
            count: prims.len() as u32,
        };
        // The depth cap keeps traversal's fixed stack from overflowing on adversarial input.
        if prims.len() <= 1 || depth + 2 >= MAX_DEPTH {
            return leaf;
        }
        // One block is a leaf whatever the split: a split costs a traversal step more.
        if prims.len() <= MAX_LEAF.min(self.align) {
            return leaf;
        }
        let Some(split) = self.find_split(prims, bounds, centroid_bounds) else {
            return leaf;
        };
        let (mid, left_centroids, right_centroids) = self.partition(prims, &split);
        if mid == 0 || mid == prims.len() {
            return leaf;
        }
        let (left, right) = prims.split_at_mut(mid);
        let (l, r) = if prims_len(left, right) >= PARALLEL_THRESHOLD {
            rayon::join(
                || self.build(left, first, depth + 1, split.left, left_centroids),
                || self.build(right, first + mid, depth + 1, split.right, right_centroids),
            )
        } else {
            (
                self.build(left, first, depth + 1, split.left, left_centroids),
                self.build(right, first + mid, depth + 1, split.right, right_centroids),
            )
        };
        Tree::Interior {
            bounds,
            children: Box::new([l, r]),
        }
    }

    /// Bins `prims` into `out` (empty on entry). Filled in place: returned by value, the
    /// 3 KiB of bins were copied once per node.
    fn bin(&self, prims: &[PrimRef], lo: [f32; 4], scale: [f32; 4], bins: usize, out: &mut Bins) {
        if prims.len() >= PARALLEL_BINNING {
            *out = prims
                .par_chunks(PARALLEL_BINNING / 2)
                .map(|chunk| {
                    let mut part = Bins::empty();
                    self.bin(chunk, lo, scale, bins, &mut part);
                    part
                })
                .reduce(Bins::empty, Bins::merge);
            return;
        }
        let last = (bins - 1) as f32;
        for PrimRef(r) in prims {
            let bin = Box4::bins_of(&r.centroid2(), &lo, &scale, last);
            for axis in 0..3 {
                let bin = bin[axis] as usize;
                out.counts[axis][bin] += 1;
                out.bounds[axis][bin].grow(r);
            }
        }
    }

    /// The cheapest binned SAH split over all three axes (binned in one pass), or None when
    /// a leaf is cheaper and small enough.
    fn find_split(&self, prims: &[PrimRef], bounds: Aabb, centroid_bounds: Box4) -> Option<Split> {
        let extent: [f32; 4] =
            std::array::from_fn(|k| centroid_bounds.hi[k] - centroid_bounds.lo[k]);
        let lo = centroid_bounds.lo;
        // Small nodes use fewer bins: as good a split for far less sweeping.
        let nbins = prims.len().clamp(2, BINS);
        // A zero scale (no extent, or an infinite one) puts every centroid in bin 0.
        let per = |e: f32| {
            let s = nbins as f32 / e;
            if e > 0.0 && s.is_finite() {
                s
            } else {
                0.0
            }
        };
        let scale = extent.map(per);
        let mut bins = Bins::empty();
        self.bin(prims, lo, scale, nbins, &mut bins);
        let mut best: Option<(f64, usize, usize)> = None;
        // Each suffix's box and count, from the right; reused across axes.
        let mut right_box = [Box4::EMPTY; BINS];
        let mut right_count = [0usize; BINS];
        // Axes without a usable extent (none, NaN or infinite) have a zero scale.
        for (axis, _) in scale[..3].iter().enumerate().filter(|(_, &s)| s > 0.0) {
            let (boxes, counts) = (&bins.bounds[axis], &bins.counts[axis]);
            let mut acc = Box4::EMPTY;
            let mut count = 0;
            for i in (1..nbins).rev() {
                acc.grow(&boxes[i]);
                count += counts[i] as usize;
                right_box[i] = acc;
                right_count[i] = count;
            }
            let mut acc = Box4::EMPTY;
            let mut count = 0;
            for split in 1..nbins {
                acc.grow(&boxes[split - 1]);
                count += counts[split - 1] as usize;
                if count == 0 || right_count[split] == 0 {
                    continue;
                }
                let cost = acc.area() * self.blocks(count)
                    + right_box[split].area() * self.blocks(right_count[split]);
                if best.is_none_or(|(c, ..)| cost < c) {
                    best = Some((cost, axis, split));
                }
            }
        }
        let (cost, axis, bin) = best?;
        // The children's boxes, for the best split only.
        // (Grown in the sweeps' orders, so that even the sign of a zero comes out the same.)
        let (mut left, mut right) = (Box4::EMPTY, Box4::EMPTY);
        for b in &bins.bounds[axis][..bin] {
            left.grow(b);
        }
        for b in bins.bounds[axis][bin..nbins].iter().rev() {
            right.grow(b);
        }
        let (left, right) = (left.aabb(), right.aabb());
        let split_cost =
            TRAVERSAL_COST + INTERSECT_COST * cost / bounds.surface_area().max(f64::MIN_POSITIVE);
        let leaf_cost = INTERSECT_COST * self.blocks(prims.len());
        if prims.len() <= self.max_leaf() && leaf_cost <= split_cost {
            return None;
        }
        Some(Split {
            axis,
            lo,
            scale,
            bins: nbins,
            bin,
            left,
            right,
        })
    }

    /// The most primitives a leaf may hold when a split costs more.
    #[inline(always)]
    fn max_leaf(&self) -> usize {
        MAX_LEAF.max(MAX_LEAF_BLOCKS * self.align)
    }

    /// The intersection cost of `n` primitives, in blocks.
    #[inline(always)]
    fn blocks(&self, n: usize) -> f64 {
        // A shift where `align` is a power of two (always, in practice): the sweeps call
        // this twice per candidate split, and an integer division cost more than the rest.
        match self.align_shift {
            Some(shift) => ((n + self.align - 1) >> shift) as f64,
            None => n.div_ceil(self.align) as f64,
        }
    }

    /// In-place partition by `split`; returns the number of primitives going left and the
    /// centroid bounds of both sides.
    fn partition(&self, prims: &mut [PrimRef], split: &Split) -> (usize, Box4, Box4) {
        // From both ends, swapping only misplaced pairs: half the moves of a one-sided pass,
        // which count now that the references themselves move.
        let (mut left, mut right) = (Box4::EMPTY, Box4::EMPTY);
        let (mut i, mut j) = (0, prims.len());
        loop {
            while i < j {
                let c = prims[i].0.centroid2();
                if !split.goes_left(&c) {
                    break;
                }
                left.grow_point(&c);
                i += 1;
            }
            while i < j {
                let c = prims[j - 1].0.centroid2();
                if split.goes_left(&c) {
                    break;
                }
                right.grow_point(&c);
                j -= 1;
            }
            if i == j {
                return (i, left, right);
            }
            // prims[i] goes right and prims[j - 1] left.
            prims.swap(i, j - 1);
        }
    }
}

fn prims_len(a: &[PrimRef], b: &[PrimRef]) -> usize {
    a.len().min(b.len())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bin_indices_truncate_clamp_and_send_nan_to_bin_zero() {
        let lo = [1.0, -2.0, 0.5, 0.0];
        let scale = [4.0, 0.5, 0.0, 0.0];
        let last = 15.0;
        let cases = [
            ([1.0, -2.0, 0.5, 0.0], [0, 0, 0, 0]),
            ([1.3, 5.9, 7.0, 0.0], [1, 3, 0, 0]),
            ([4.74, 28.0, -1.0, 0.0], [14, 15, 0, 0]),
            ([0.0, -1e30, f32::NAN, 0.0], [0, 0, 0, 0]),
            ([f32::NAN, 1e30, f32::INFINITY, 0.0], [0, 15, 0, 0]),
            ([f32::INFINITY, f32::NEG_INFINITY, 3.0, 0.0], [15, 0, 0, 0]),
        ];
        for (c, want) in cases {
            assert_eq!(Box4::bins_of(&c, &lo, &scale, last), want, "{c:?}");
        }
    }

    #[test]
    fn references_keep_their_index_and_contain_their_bounds() {
        let b = Aabb {
            min: DVec3::new(0.1, -1e5 - 0.001, 1e-7),
            max: DVec3::new(0.3, 1e30, 2e-7),
        };
        for id in [0, 1, 12345, MAX_PRIMS as u32 - 1] {
            let r = PrimRef::of(&b, id);
            assert_eq!(r.id(), id);
            assert!(r.0.lo[3].is_normal());
            let f = r.0.aabb();
            assert!(f.min.cmple(b.min).all() && f.max.cmpge(b.max).all());
            assert_eq!(r.0.centroid2()[3], 0.0);
        }
    }
}
