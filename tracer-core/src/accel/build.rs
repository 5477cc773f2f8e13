//! Building a [`Bvh`]: binned SAH over the primitives' bounds, large subtrees in parallel,
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
        let mut order: Vec<u32> = (0..bounds.len() as u32).collect();
        if bounds.is_empty() {
            return Bvh::default();
        }
        let (root_bounds, root_centroids) = bounds
            .par_iter()
            .fold(
                || (Aabb::EMPTY, Aabb::EMPTY),
                |(b, c), pb| (b.union(*pb), c.grow(pb.centroid())),
            )
            .reduce(
                || (Aabb::EMPTY, Aabb::EMPTY),
                |(b0, c0), (b1, c1)| (b0.union(b1), c0.union(c1)),
            );
        let builder = Builder {
            bounds,
            align,
            align_shift: align.is_power_of_two().then(|| align.trailing_zeros()),
        };
        let mut tree = builder.build(&mut order, 0, 0, root_bounds, root_centroids);
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

struct Builder<'a> {
    /// The primitives' bounds. Centroids are worked out from them where needed (the same
    /// values): an array of them cost 24 bytes per primitive, 240 MB for 10M triangles, and
    /// the time the kernel took to hand out and zero those pages.
    bounds: &'a [Aabb],
    /// The owner tests primitives in blocks of this many at the cost of one.
    align: usize,
    /// log2(`align`) where `align` is a power of two.
    align_shift: Option<u32>,
}

/// Primitives whose centroid falls in a bin below `bin` on `axis` go to the left child.
struct Split {
    axis: usize,
    lo: f64,
    scale: f64,
    bins: usize,
    bin: usize,
    /// The children's bounds, from the bins.
    left: Aabb,
    right: Aabb,
}

impl Split {
    #[inline(always)]
    fn goes_left(&self, centroid: f64) -> bool {
        bin_of(centroid, self.lo, self.scale, self.bins) < self.bin
    }
}

/// A box as (min x, y, z, +∞, −max x, y, z, +∞): growing it is one lane-wise minimum over
/// eight lanes, which compiles to a few SIMD min instructions (the six scalar compare-and-
/// selects it replaces were most of the binning's time). Negation is exact, so the maxima
/// read back are the same f64 values.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct BinBox([f64; 8]);

const EMPTY_BIN: BinBox = BinBox([f64::INFINITY; 8]);

impl BinBox {
    #[inline(always)]
    fn of(b: &Aabb) -> BinBox {
        let inf = f64::INFINITY;
        BinBox([
            b.min.x, b.min.y, b.min.z, inf, -b.max.x, -b.max.y, -b.max.z, inf,
        ])
    }

    /// `self` grown by `b`. Like `f64::min` (and the former scalar code, tie for tie), a NaN
    /// in `b` leaves `self` as it was.
    #[inline(always)]
    fn grow(&mut self, b: &BinBox) {
        for k in 0..8 {
            self.0[k] = if b.0[k] < self.0[k] {
                b.0[k]
            } else {
                self.0[k]
            };
        }
    }

    /// Surface area of a non-empty box (the sweeps only measure boxes holding primitives).
    #[inline(always)]
    fn area(&self) -> f64 {
        let b = &self.0;
        let (x, y, z) = (-b[4] - b[0], -b[5] - b[1], -b[6] - b[2]);
        2.0 * (x * y + y * z + z * x)
    }

    fn aabb(&self) -> Aabb {
        let b = &self.0;
        Aabb {
            min: DVec3::new(b[0], b[1], b[2]),
            max: DVec3::new(-b[4], -b[5], -b[6]),
        }
    }
}

/// Per axis and bin: the union of the primitives' bounds and their number.
#[derive(Clone)]
struct Bins {
    bounds: [[BinBox; BINS]; 3],
    counts: [[u32; BINS]; 3],
}

impl Bins {
    fn empty() -> Bins {
        Bins {
            bounds: [[EMPTY_BIN; BINS]; 3],
            counts: [[0; BINS]; 3],
        }
    }

    /// Exact (min and integer sums), so any grouping of the merges gives the same bins.
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

impl Builder<'_> {
    /// `bounds` and `centroid_bounds` are those of `prims`, found by the caller.
    fn build(
        &self,
        prims: &mut [u32],
        first: usize,
        depth: usize,
        bounds: Aabb,
        centroid_bounds: Aabb,
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
    fn bin(&self, prims: &[u32], lo: DVec3, scale: DVec3, bins: usize, out: &mut Bins) {
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
        for &p in prims {
            let bounds = &self.bounds[p as usize];
            let (c, b) = (bounds.centroid(), BinBox::of(bounds));
            for axis in 0..3 {
                let bin = bin_of(c[axis], lo[axis], scale[axis], bins);
                out.counts[axis][bin] += 1;
                out.bounds[axis][bin].grow(&b);
            }
        }
    }

    /// The cheapest binned SAH split over all three axes (binned in one pass), or None when
    /// a leaf is cheaper and small enough.
    fn find_split(&self, prims: &[u32], bounds: Aabb, centroid_bounds: Aabb) -> Option<Split> {
        let extent = centroid_bounds.extent();
        let lo = centroid_bounds.min;
        // Small nodes use fewer bins: as good a split for far less sweeping.
        let nbins = prims.len().clamp(2, BINS);
        let per = |e: f64| if e > 0.0 { nbins as f64 / e } else { 0.0 };
        let scale = DVec3::new(per(extent.x), per(extent.y), per(extent.z));
        let mut bins = Bins::empty();
        self.bin(prims, lo, scale, nbins, &mut bins);
        let mut best: Option<(f64, usize, usize)> = None;
        // Each suffix's box and count, from the right; reused across axes.
        let mut right_box = [EMPTY_BIN; BINS];
        let mut right_count = [0usize; BINS];
        for axis in 0..3 {
            // NaN extents are skipped too.
            let usable = extent[axis] > 0.0;
            if !usable {
                continue;
            }
            let (boxes, counts) = (&bins.bounds[axis], &bins.counts[axis]);
            let mut acc = EMPTY_BIN;
            let mut count = 0;
            for i in (1..nbins).rev() {
                acc.grow(&boxes[i]);
                count += counts[i] as usize;
                right_box[i] = acc;
                right_count[i] = count;
            }
            let mut acc = EMPTY_BIN;
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
        let (mut left, mut right) = (EMPTY_BIN, EMPTY_BIN);
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
            lo: lo[axis],
            scale: scale[axis],
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
    fn partition(&self, prims: &mut [u32], split: &Split) -> (usize, Aabb, Aabb) {
        let (mut left, mut right) = (Aabb::EMPTY, Aabb::EMPTY);
        let mut i = 0;
        for j in 0..prims.len() {
            let c = self.bounds[prims[j] as usize].centroid();
            if split.goes_left(c[split.axis]) {
                left = left.grow(c);
                prims.swap(i, j);
                i += 1;
            } else {
                right = right.grow(c);
            }
        }
        (i, left, right)
    }
}

fn prims_len(a: &[u32], b: &[u32]) -> usize {
    a.len().min(b.len())
}

#[inline(always)]
fn bin_of(c: f64, lo: f64, scale: f64, bins: usize) -> usize {
    (((c - lo) * scale) as usize).min(bins - 1)
}
