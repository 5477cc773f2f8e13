//! Building a [`Bvh`]: binned SAH over the primitives' bounds (rounded outward to f32, binned
//! with f32 SIMD min/max, the references partitioned in place), collapsed into `WIDTH`-wide
//! nodes with outward-rounded f32 boxes as it is built (no binary tree is kept), large
//! subtrees in parallel.

use glam::DVec3;
use rayon::prelude::*;

use super::bvh::{round_down, round_up, Bvh, Node, MAX_DEPTH, NO_CHILD, WIDTH};
use super::memory::with_capacity_huge;
use crate::geometry::Aabb;

const BINS: usize = 16;
const _: () = assert!(BINS.is_power_of_two());
const MAX_LEAF: usize = 4;
/// With primitives in blocks, a leaf may hold this many blocks when the SAH finds that
/// cheaper than splitting: a second block in a leaf costs less than the node visit a split
/// adds (fewer, shallower nodes; 10% more incoherent rays per second on dragon).
const MAX_LEAF_BLOCKS: usize = 2;
const TRAVERSAL_COST: f64 = 1.0;
const INTERSECT_COST: f64 = 1.0;
/// Subtrees at least this large are built on another rayon task.
const PARALLEL_THRESHOLD: usize = 4096;

/// A node of the binary SAH tree: a range of the references with its bounds.
#[derive(Clone, Copy)]
struct Part {
    /// Where the range starts in the whole reference array.
    first: usize,
    len: usize,
    /// Depth in the binary tree (the root's is 0).
    depth: usize,
    bounds: Aabb,
    centroids: Box4,
}

/// A binary node once decided: a leaf, or split with its references partitioned between the
/// two children.
// Slots live in a fixed array on the stack, written once each; boxing the split variant
// would allocate per binary node, which is what this builder stopped doing.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Copy)]
enum Slot {
    /// A leaf; with the best split of its references where it holds more than one block
    /// and the SAH found the leaf cheaper, for [`Builder::wide`] to use where its wide node
    /// has a free slot.
    Leaf(Part, Option<Split>),
    Split(Part, [Part; 2]),
}

impl Slot {
    fn part(&self) -> &Part {
        match self {
            Slot::Leaf(p, _) | Slot::Split(p, _) => p,
        }
    }
}

/// Wide nodes in depth-first order, the leaves' primitive order (padded per leaf) and the
/// binary tree's depth, of the whole tree or of a subtree built on its own task; in the
/// latter, child indices count from the subtree's first node and leaf slots from its first
/// slot until [`Out::append`] moves them.
struct Out {
    nodes: Vec<Node>,
    order: Vec<u32>,
    depth: usize,
}

impl Out {
    fn new() -> Out {
        Out {
            nodes: Vec::new(),
            order: Vec::new(),
            depth: 0,
        }
    }

    /// Appends a wide node with `slots`' boxes (links still unset); returns its index.
    fn push_node(&mut self, slots: &[&Slot]) -> usize {
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
            leaves: 0,
        };
        for (c, slot) in slots.iter().enumerate() {
            let b = to_f32_box(slot.part().bounds);
            for a in 0..3 {
                node.bounds[2 * a][c] = b[a];
                node.bounds[2 * a + 1][c] = b[a + 3];
            }
        }
        self.nodes.push(node);
        self.nodes.len() - 1
    }

    /// Makes slot `c` of node `index` the leaf `part` (its references `prims`): its
    /// primitives join the order, the leaf starting on a multiple of `align`.
    fn leaf(&mut self, index: usize, c: usize, part: &Part, prims: &[PrimRef], align: usize) {
        let start = self.order.len();
        self.order.extend(prims.iter().map(PrimRef::id));
        self.order
            .resize(self.order.len().next_multiple_of(align), PADDING);
        self.nodes[index].index[c] = start as u32;
        let node = &mut self.nodes[index];
        // Leaves hold at most `Builder::max_leaf` primitives.
        node.count[c] = u16::try_from(part.len).expect("a leaf of at most a few primitives");
        node.leaves |= 1 << c;
        self.depth = self.depth.max(part.depth + 1);
    }

    /// Appends a subtree built on its own, its links moved to their new places; returns the
    /// index of its first node.
    fn append(&mut self, sub: Out) -> u32 {
        let (node_base, slot_base) = (self.nodes.len() as u32, self.order.len() as u32);
        self.nodes.extend(sub.nodes.iter().map(|n| {
            let mut n = *n;
            for c in 0..WIDTH {
                if n.count[c] > 0 {
                    n.index[c] += slot_base;
                } else if n.index[c] != NO_CHILD {
                    n.index[c] += node_base;
                }
            }
            n
        }));
        self.order.extend_from_slice(&sub.order);
        self.depth = self.depth.max(sub.depth);
        node_base
    }
}

impl Bvh {
    /// Builds with the binned surface-area heuristic (16 bins on each axis), the binary tree
    /// collapsed into `WIDTH`-wide nodes as it is built, large subtrees in parallel. The
    /// result does not depend on the thread count.
    pub fn build(bounds: &[Aabb]) -> Bvh {
        Bvh::build_aligned(bounds, 1)
    }

    /// Like [`Bvh::build`], with every leaf's first slot a multiple of `align`: `order` is
    /// padded with [`PADDING`] slots, so that an owner can keep its primitives in blocks of
    /// `align` with no leaf straddling two blocks it does not need.
    pub fn build_aligned(bounds: &[Aabb], align: usize) -> Bvh {
        Bvh::build_with(bounds, align, INTERSECT_COST)
    }

    /// Like [`Bvh::build`], for primitives whose test costs `intersect_cost` node visits
    /// each (on average) rather than one: the SAH then gives costly primitives leaves of
    /// their own sooner, so that a ray tests only those whose boxes it meets.
    pub fn build_costed(bounds: &[Aabb], intersect_cost: f64) -> Bvh {
        Bvh::build_with(bounds, 1, intersect_cost)
    }

    fn build_with(bounds: &[Aabb], align: usize, intersect_cost: f64) -> Bvh {
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
            intersect_cost,
        };
        let root = Part {
            first: 0,
            len: refs.len(),
            depth: 0,
            bounds: root_bounds,
            centroids: root_centroids,
        };
        let padded = if align > 1 { refs.len() / 2 } else { 0 };
        let mut out = Out {
            nodes: with_capacity_huge(bounds.len() / 4 + 1),
            order: Vec::with_capacity(refs.len() + padded),
            depth: 0,
        };
        match builder.decide(&mut refs, root) {
            Slot::Split(_, children) => builder.wide(&mut refs, 0, children, &mut out),
            leaf @ Slot::Leaf(part, _) => {
                // A lone leaf: one node with one used slot.
                let index = out.push_node(&[&leaf]);
                out.leaf(index, 0, &part, &refs, align);
            }
        }
        Bvh {
            nodes: out.nodes,
            order: out.order,
            bounds: Some(root_bounds),
            reach: super::bvh::reach(&root_bounds),
            depth: out.depth,
            spans: Vec::new(),
        }
    }
}

/// Marks a padding slot in the `order` of [`Bvh::build_aligned`].
pub const PADDING: u32 = u32::MAX;

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

struct Builder {
    /// The owner tests primitives in blocks of this many at the cost of one.
    align: usize,
    /// log2(`align`) where `align` is a power of two.
    align_shift: Option<u32>,
    /// The SAH's cost of testing a block of primitives, in node visits.
    intersect_cost: f64,
}

/// Primitives whose centroid falls in a bin below `bin` on `axis` go to the left child.
#[derive(Clone, Copy)]
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
    #[cfg(not(target_arch = "x86_64"))]
    #[inline(always)]
    fn centroid2(&self) -> [f32; 4] {
        std::array::from_fn(|k| if k < 3 { self.lo[k] + self.hi[k] } else { 0.0 })
    }

    /// The portable version's sums in one SSE add, the fourth lane masked to +0 (built lane
    /// by lane, the compiler shuffled scalars into place for every reference).
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn centroid2(&self) -> [f32; 4] {
        use std::arch::x86_64::*;
        // SAFETY: SSE2 is part of the x86_64 baseline; a Box4's halves are 16-byte aligned
        // (the struct is 32-byte aligned, `hi` at offset 16).
        unsafe {
            let keep = _mm_castsi128_ps(_mm_set_epi32(0, -1, -1, -1));
            let sum = _mm_add_ps(_mm_load_ps(self.lo.as_ptr()), _mm_load_ps(self.hi.as_ptr()));
            let mut out = [0.0; 4];
            _mm_storeu_ps(out.as_mut_ptr(), _mm_and_ps(sum, keep));
            out
        }
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
    ///
    /// In SSE: the portable form's selects write back lanes only where they change, and the
    /// compiler made them masked stores (`vmaskmovps`) once AVX was in the build, microcoded
    /// on AMD: binning took 4.6 times as long. `minps(b, a)` is `b < a ? b : a`, lane for
    /// lane the same selects.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn grow(&mut self, b: &Box4) {
        use std::arch::x86_64::*;
        // SAFETY: SSE is part of the x86_64 baseline; a Box4's halves are 16-byte aligned
        // (the struct is 32-byte aligned, `hi` at offset 16).
        unsafe {
            let lo = _mm_min_ps(_mm_load_ps(b.lo.as_ptr()), _mm_load_ps(self.lo.as_ptr()));
            let hi = _mm_max_ps(_mm_load_ps(b.hi.as_ptr()), _mm_load_ps(self.hi.as_ptr()));
            _mm_store_ps(self.lo.as_mut_ptr(), lo);
            _mm_store_ps(self.hi.as_mut_ptr(), hi);
        }
    }

    #[cfg(not(target_arch = "x86_64"))]
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

    fn aabb(&self) -> Aabb {
        Aabb {
            min: DVec3::new(self.lo[0] as f64, self.lo[1] as f64, self.lo[2] as f64),
            max: DVec3::new(self.hi[0] as f64, self.hi[1] as f64, self.hi[2] as f64),
        }
    }
}

/// One side of every candidate split of an axis, in columns: the extents of its box and its
/// number of primitives (entries outside the candidates are zero, or unused).
#[derive(Default)]
struct Sides {
    x: [f32; BINS],
    y: [f32; BINS],
    z: [f32; BINS],
    count: [u32; BINS],
}

impl Sides {
    #[inline(always)]
    fn set(&mut self, split: usize, b: &Box4, count: u32) {
        self.x[split] = b.hi[0] - b.lo[0];
        self.y[split] = b.hi[1] - b.lo[1];
        self.z[split] = b.hi[2] - b.lo[2];
        self.count[split] = count;
    }

    /// The surface areas of the first `lanes` entries (only those holding primitives are
    /// read). Lane by lane the same f32 operations in the same order as one box at a time,
    /// so the costs, and the tree, do not change; in columns they compile to SIMD.
    #[inline(always)]
    fn areas(&self, lanes: usize) -> [f32; BINS] {
        let mut out = [0.0; BINS];
        let extents = self.x.iter().zip(&self.y).zip(&self.z);
        for (a, ((&x, &y), &z)) in out[..lanes].iter_mut().zip(extents) {
            *a = 2.0 * (x * y + y * z + z * x);
        }
        out
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
    /// Decides the binary node `part`, whose references are `prims`: a leaf, or split with
    /// `prims` partitioned between its children.
    fn decide(&self, prims: &mut [PrimRef], part: Part) -> Slot {
        // The depth cap keeps traversal's fixed stack from overflowing on adversarial input.
        if prims.len() <= 1 || part.depth + 2 >= MAX_DEPTH {
            return Slot::Leaf(part, None);
        }
        // One block is a leaf whatever the split: a split costs a traversal step more.
        if prims.len() <= MAX_LEAF.min(self.align) {
            return Slot::Leaf(part, None);
        }
        let Some((split, leaf_cheaper)) = self.find_split(prims, part.bounds, part.centroids)
        else {
            return Slot::Leaf(part, None);
        };
        if leaf_cheaper {
            let openable = self.align > 1 && prims.len() > self.align;
            return Slot::Leaf(part, openable.then_some(split));
        }
        self.split_at(prims, part, &split)
            .unwrap_or(Slot::Leaf(part, None))
    }

    /// Partitions `prims` (the references of `part`) by `split`: the split node, or None
    /// where every reference falls on one side.
    fn split_at(&self, prims: &mut [PrimRef], part: Part, split: &Split) -> Option<Slot> {
        let (mid, left_centroids, right_centroids) = self.partition(prims, split);
        if mid == 0 || mid == prims.len() {
            return None;
        }
        let child = |first, len, bounds, centroids| Part {
            first,
            len,
            depth: part.depth + 1,
            bounds,
            centroids,
        };
        Some(Slot::Split(
            part,
            [
                child(part.first, mid, split.left, left_centroids),
                child(
                    part.first + mid,
                    prims.len() - mid,
                    split.right,
                    right_centroids,
                ),
            ],
        ))
    }

    /// Decides both children of a split node into `out[0]` and `out[1]`; `prims` holds
    /// exactly their references.
    fn decide_pair(&self, prims: &mut [PrimRef], children: [Part; 2], out: &mut [Option<Slot>]) {
        let (left, right) = prims.split_at_mut(children[0].len);
        let (l, r) = out.split_at_mut(1);
        if left.len().min(right.len()) >= PARALLEL_THRESHOLD {
            rayon::join(
                || l[0] = Some(self.decide(left, children[0])),
                || r[0] = Some(self.decide(right, children[1])),
            );
        } else {
            l[0] = Some(self.decide(left, children[0]));
            r[0] = Some(self.decide(right, children[1]));
        }
    }

    /// Appends to `out` the wide node that replaces a split binary node, then its subtrees
    /// depth first. `prims` are the node's references, starting at `base` in the whole array;
    /// `children` its binary children. The binary tree is opened below the node, its widest
    /// split slot first (by surface area, the last of equals), until it has `WIDTH` slots.
    fn wide(&self, prims: &mut [PrimRef], base: usize, children: [Part; 2], out: &mut Out) {
        // The decided binary nodes, written once; the slots are indices into them, so that
        // opening one moves bytes instead of 400-byte slots.
        let mut decided: [Option<Slot>; 2 * WIDTH - 2] = [None; 2 * WIDTH - 2];
        let mut order = [0u8; WIDTH];
        self.decide_pair(prims, children, &mut decided[..2]);
        order[1] = 1;
        let (mut len, mut used) = (2, 2);
        // Leaves that keep a split are opened too, as Embree's builder does: in a free slot
        // the split adds no node to visit, only box tests the node makes anyway, and a ray
        // then tests only the blocks of the halves it meets (the SAH cost of the dragon's
        // tree falls by 8%, to Embree's). Not where the split parts nothing
        // (`unsplittable`, by index into `decided`).
        let mut unsplittable = 0u32;
        while len < WIDTH {
            let mut widest: Option<(usize, f64)> = None;
            for (i, &k) in order[..len].iter().enumerate() {
                let part = match &decided[k as usize] {
                    Some(Slot::Split(part, _)) => part,
                    Some(Slot::Leaf(part, Some(_))) if unsplittable & (1 << k) == 0 => part,
                    _ => continue,
                };
                let area = part.bounds.surface_area();
                if widest.is_none_or(|(_, w)| area.total_cmp(&w).is_ge()) {
                    widest = Some((i, area));
                }
            }
            let Some((i, _)) = widest else { break };
            let k = order[i] as usize;
            if let Some(Slot::Leaf(part, Some(split))) = decided[k] {
                let range = &mut prims[part.first - base..][..part.len];
                match self.split_at(range, part, &split) {
                    Some(slot) => decided[k] = Some(slot),
                    None => {
                        unsplittable |= 1 << k;
                        continue;
                    }
                }
            }
            let Some(Slot::Split(part, children)) = decided[k] else {
                unreachable!()
            };
            let range = &mut prims[part.first - base..][..part.len];
            self.decide_pair(range, children, &mut decided[used..used + 2]);
            order.copy_within(i + 1..len, i + 2);
            order[i] = used as u8;
            order[i + 1] = used as u8 + 1;
            used += 2;
            len += 1;
        }
        let slot = |c: usize| decided[order[c] as usize].as_ref().expect("decided above");
        let slots: [&Slot; WIDTH] = std::array::from_fn(|c| slot(c.min(len - 1)));
        let slots = &slots[..len];
        let index = out.push_node(slots);
        if prims.len() < 2 * PARALLEL_THRESHOLD {
            for (c, slot) in slots.iter().enumerate() {
                let range = &mut prims[slot.part().first - base..][..slot.part().len];
                match slot {
                    Slot::Leaf(part, _) => out.leaf(index, c, part, range, self.align),
                    Slot::Split(part, children) => {
                        let child = out.nodes.len() as u32;
                        self.wide(range, part.first, *children, out);
                        out.nodes[index].index[c] = child;
                    }
                }
            }
            return;
        }
        // Large: the split slots' subtrees are built on their own tasks, then appended in
        // slot order, so the layout is the same as built in one.
        let mut rest = &mut *prims;
        let pieces: Vec<(&mut [PrimRef], &Slot)> = slots
            .iter()
            .map(|&slot| {
                let (head, tail) = std::mem::take(&mut rest).split_at_mut(slot.part().len);
                rest = tail;
                (head, slot)
            })
            .collect();
        let subtrees: Vec<Option<Out>> = pieces
            .into_par_iter()
            .map(|(range, slot)| match slot {
                Slot::Leaf(..) => None,
                Slot::Split(part, children) => {
                    let mut sub = Out::new();
                    self.wide(range, part.first, *children, &mut sub);
                    Some(sub)
                }
            })
            .collect();
        for (c, (slot, sub)) in slots.iter().zip(subtrees).enumerate() {
            match slot {
                Slot::Leaf(part, _) => out.leaf(
                    index,
                    c,
                    part,
                    &prims[part.first - base..][..part.len],
                    self.align,
                ),
                Slot::Split(..) => {
                    out.nodes[index].index[c] = out.append(sub.expect("built above"));
                }
            }
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
                // Within 0..BINS already: the mask only spares a bounds check.
                let bin = bin[axis] as usize & (BINS - 1);
                out.counts[axis][bin] += 1;
                out.bounds[axis][bin].grow(r);
            }
        }
    }

    /// The cheapest binned SAH split over all three axes (binned in one pass), or None when
    /// a leaf is cheaper and small enough.
    // Out of line (one call per node): profiles show the sweep and the partition apart.
    #[inline(never)]
    /// The best binned SAH split of `prims` (None where there is none), and whether a leaf
    /// of them costs no more.
    fn find_split(
        &self,
        prims: &[PrimRef],
        bounds: Aabb,
        centroid_bounds: Box4,
    ) -> Option<(Split, bool)> {
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
        // Candidates 1..nbins; the columns are worked out in groups of four lanes.
        let lanes = nbins.next_multiple_of(4);
        // Axes without a usable extent (none, NaN or infinite) have a zero scale.
        for (axis, _) in scale[..3].iter().enumerate().filter(|(_, &s)| s > 0.0) {
            let (boxes, counts) = (&bins.bounds[axis], &bins.counts[axis]);
            // Split `s` sends bins below `s` left: each side's box (as extents) and count.
            let (mut left, mut right) = (Sides::default(), Sides::default());
            let mut acc = Box4::EMPTY;
            let mut count = 0;
            for i in (1..nbins).rev() {
                acc.grow(&boxes[i]);
                count += counts[i];
                right.set(i, &acc, count);
            }
            let mut acc = Box4::EMPTY;
            let mut count = 0;
            for split in 1..nbins {
                acc.grow(&boxes[split - 1]);
                count += counts[split - 1];
                left.set(split, &acc, count);
            }
            let (left_area, right_area) = (left.areas(lanes), right.areas(lanes));
            let (left_blocks, right_blocks) =
                (self.blocks_of(&left, lanes), self.blocks_of(&right, lanes));
            let mut cost = [0.0; BINS];
            for k in 0..lanes {
                cost[k] =
                    left_area[k] as f64 * left_blocks[k] + right_area[k] as f64 * right_blocks[k];
            }
            for (split, &c) in cost.iter().enumerate().take(nbins).skip(1) {
                if left.count[split] == 0 || right.count[split] == 0 {
                    continue;
                }
                if best.is_none_or(|(b, ..)| c < b) {
                    best = Some((c, axis, split));
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
        let split_cost = TRAVERSAL_COST
            + self.intersect_cost * cost / bounds.surface_area().max(f64::MIN_POSITIVE);
        let leaf_cost = self.intersect_cost * self.blocks(prims.len());
        let leaf_cheaper = prims.len() <= self.max_leaf() && leaf_cost <= split_cost;
        let split = Split {
            axis,
            lo,
            scale,
            bins: nbins,
            bin,
            left,
            right,
        };
        Some((split, leaf_cheaper))
    }

    /// The most primitives a leaf may hold when a split costs more.
    #[inline(always)]
    fn max_leaf(&self) -> usize {
        MAX_LEAF.max(MAX_LEAF_BLOCKS * self.align)
    }

    /// [`Builder::blocks`] of the first `lanes` counts of `sides`.
    #[inline(always)]
    fn blocks_of(&self, sides: &Sides, lanes: usize) -> [f64; BINS] {
        let mut out = [0.0; BINS];
        let blocks = out[..lanes].iter_mut().zip(&sides.count);
        match self.align_shift {
            // Counts stay below 2^31 (MAX_PRIMS): the sum does not wrap, and converting
            // through i32 is exact and takes one SSE2 instruction per two lanes.
            Some(shift) => {
                for (b, &n) in blocks {
                    *b = ((n + (self.align as u32 - 1)) >> shift) as i32 as f64;
                }
            }
            None => {
                for (b, &n) in blocks {
                    *b = self.blocks(n as usize);
                }
            }
        }
        out
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
    #[inline(never)]
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

#[cfg(test)]
mod tests {
    use super::*;

    /// Boxes scattered as a mesh's triangles would be: many, small, some long and thin.
    fn scattered(n: usize) -> Vec<Aabb> {
        let mut next = crate::test_rng::uniform(20261202);
        (0..n)
            .map(|i| {
                let c = DVec3::new(next(), next(), next()) * 100.0;
                let long = if i % 13 == 0 { 20.0 } else { 1.0 };
                let e = DVec3::new(next() * long, next(), next()) * 0.4;
                Aabb {
                    min: c - e,
                    max: c + e,
                }
            })
            .collect()
    }

    #[test]
    fn subtrees_built_apart_link_to_their_own_nodes_and_leaves() {
        // Large enough that the wide nodes near the root build their subtrees as separate
        // `Out`s and append them, moving their links.
        let prims = scattered(40_000);
        for align in [1, 4] {
            let bvh = Bvh::build_aligned(&prims, align);
            // From the root, every node is reached once and every primitive once, inside
            // its leaf's box.
            let mut reached = vec![0; bvh.nodes.len()];
            let mut seen = vec![0; prims.len()];
            let mut stack = vec![0];
            while let Some(i) = stack.pop() {
                reached[i] += 1;
                let n = &bvh.nodes[i];
                for c in 0..WIDTH {
                    assert_eq!(
                        n.leaves >> c & 1 == 1,
                        n.count[c] > 0,
                        "leaf mask of slot {c}"
                    );
                    if n.count[c] > 0 {
                        assert_eq!(n.index[c] as usize % align, 0);
                        for slot in n.index[c]..n.index[c] + u32::from(n.count[c]) {
                            let p = bvh.order[slot as usize] as usize;
                            seen[p] += 1;
                            let (lo, hi) = (prims[p].min, prims[p].max);
                            let b = n.bounds.map(|plane| plane[c] as f64);
                            assert!(b[0] <= lo.x && b[2] <= lo.y && b[4] <= lo.z);
                            assert!(b[1] >= hi.x && b[3] >= hi.y && b[5] >= hi.z);
                        }
                    } else if n.index[c] != NO_CHILD {
                        // Depth-first: children follow their parent.
                        assert!(n.index[c] as usize > i);
                        stack.push(n.index[c] as usize);
                    }
                }
            }
            assert!(reached.iter().all(|&r| r == 1));
            assert!(seen.iter().all(|&s| s == 1));
        }
    }

    /// A node with a free slot holds no leaf of more than one block: such a leaf is split
    /// into the free slots (the primitives here are distinct, so every one can be), in the
    /// small and the parallel builds. Every primitive still sits in exactly one leaf.
    #[test]
    fn leaves_of_several_blocks_are_split_into_free_slots() {
        for n in [40, 700, 20_000] {
            let prims = scattered(n);
            let bvh = Bvh::build_aligned(&prims, 4);
            let mut seen = vec![0u32; n];
            let mut several = 0;
            for node in &bvh.nodes {
                let used = node.index.iter().filter(|&&i| i != NO_CHILD).count();
                for c in (0..WIDTH).filter(|&c| node.leaves & (1 << c) != 0) {
                    let count = node.count[c] as usize;
                    assert!(
                        used == WIDTH || count <= 4,
                        "a leaf of {count} in a node of {used} children ({n} primitives)"
                    );
                    several += (count > 4) as usize;
                    let first = node.index[c] as usize;
                    for &id in &bvh.order[first..first + count] {
                        seen[id as usize] += 1;
                    }
                }
            }
            assert!(seen.iter().all(|&k| k == 1), "{n} primitives");
            if n == 20_000 {
                // Full nodes still take leaves of two blocks where the SAH prefers them.
                assert!(several > 0);
            }
        }
    }

    /// Overlapping boxes share leaves where testing them costs what a node visit does, and
    /// get leaves of their own where each costs four (mesh instances at the top level).
    #[test]
    fn costly_primitives_get_leaves_of_their_own() {
        let prims = crate::test_rng::boxes(4, 2000, 40.0, 1.0, 3.0);
        let largest_leaf = |bvh: &Bvh| {
            let leaves = bvh.nodes.iter().flat_map(|node| {
                (0..WIDTH)
                    .filter(|&c| node.leaves & (1 << c) != 0)
                    .map(|c| node.count[c])
            });
            leaves.max().unwrap()
        };
        assert!(largest_leaf(&Bvh::build(&prims)) > 1);
        let costed = Bvh::build_costed(&prims, 4.0);
        assert_eq!(largest_leaf(&costed), 1);
        let mut order = costed.order.clone();
        order.sort();
        assert!(order.iter().copied().eq(0..2000));
    }

    #[test]
    fn the_tree_is_the_same_bits_on_one_thread_and_four() {
        let prims = scattered(40_000);
        let pool = |n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let (one, four) = (pool(1), pool(4));
        for align in [1, 4] {
            let a = one.install(|| Bvh::build_aligned(&prims, align));
            let b = four.install(|| Bvh::build_aligned(&prims, align));
            assert_eq!(a.order, b.order);
            assert_eq!(a.depth, b.depth);
            assert_eq!(a.nodes.len(), b.nodes.len());
            for (m, n) in a.nodes.iter().zip(&b.nodes) {
                assert_eq!(m.index, n.index);
                assert_eq!(m.count, n.count);
                let bits = |n: &Node| n.bounds.map(|p| p.map(f32::to_bits));
                assert_eq!(bits(m), bits(n));
            }
        }
    }

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
