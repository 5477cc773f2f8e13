use std::mem::MaybeUninit;

use crate::geometry::{Aabb, Ray};

mod packet;
pub use packet::{PacketBounds, Spread, PACKET};

/// Children per node. Eight halve the depth of a four-wide tree, so a ray makes fewer
/// dependent node loads (the latency that bounds incoherent rays); each visit tests its
/// boxes in two SSE halves.
pub const WIDTH: usize = 8;

/// A node's child boxes in SoA f32: row `2 * axis` the minima, `2 * axis + 1` the maxima.
pub(crate) type Bounds = [[f32; WIDTH]; 6];

/// A `WIDTH`-wide BVH node: the boxes of up to `WIDTH` children in SoA f32 (four children
/// per SIMD register per plane), so one visit tests every box at once. Boxes are rounded
/// outward from f64, so they always contain the primitives' own bounds.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub struct Node {
    /// `bounds[2 * axis]` holds the children's minima on `axis`, `bounds[2 * axis + 1]`
    /// their maxima. Unused slots hold an empty box (min +∞, max −∞) that nothing hits.
    pub bounds: [[f32; WIDTH]; 6],
    /// Per child: the child node's index, or a leaf's first primitive slot.
    pub index: [u32; WIDTH],
    /// Per child: 0 for an interior child (or an unused slot), else the leaf's primitive count.
    pub count: [u16; WIDTH],
    /// Bit c set where child c is a leaf (`count[c] > 0`): stored, since the walk needs it at
    /// every visit and deriving it from the counts took about 20 instructions a visit.
    pub leaves: u8,
}

/// A BVH over primitives known only by their bounds; the owner intersects them through a
/// closure, so this module knows no geometry.
#[derive(Clone, Debug, Default)]
pub struct Bvh {
    pub nodes: Vec<Node>,
    /// `order[i]` is the original index of the primitive the owner must store at slot i.
    pub order: Vec<u32>,
    pub(super) bounds: Option<Aabb>,
    /// Per axis, a bound on every box coordinate's magnitude (from `bounds`, see
    /// [`reach`]): the f32 slab test's margin scales with it, and it is made once here
    /// rather than for every ray.
    pub(super) reach: [f64; 3],
    pub(super) depth: usize,
    /// Per node, when made by [`Bvh::with_spans`]: the first and one past the last primitive
    /// slot of the leaves below it, so that packet traversal can have a small subtree's
    /// leaves fetched as early as its node (see [`Fetch::Subtree`]). Empty otherwise.
    pub spans: Vec<[u32; 2]>,
}

/// What a packet traversal's `fetch` hint names (see [`Bvh::traverse_packet`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fetch {
    /// A leaf some ray of the packet is about to test.
    Leaf,
    /// The leaves below a node the packet is about to enter (at most
    /// [`SUBTREE_FETCH_SLOTS`] slots): some of them will likely be tested.
    Subtree,
}

/// The most primitive slots a [`Fetch::Subtree`] hint names: a node of leaves holds 8 to 32.
pub const SUBTREE_FETCH_SLOTS: u32 = 32;

/// The deepest binary tree the builder makes; a wide node is never deeper.
pub(super) const MAX_DEPTH: usize = 96;
/// Each level of the wide tree pushes at most `WIDTH - 1` siblings.
const STACK_DEPTH: usize = (WIDTH - 1) * MAX_DEPTH;
/// Marks an unused child slot.
pub(super) const NO_CHILD: u32 = u32::MAX;

/// Outward rounding margins of the f32 slab test. Each slab distance is off by at most about
/// 4 f32 rounding units (origin rounding is taken care of by choosing the rounded-up or down
/// origin per plane); 2^-20 is 16 units. The absolute term covers subnormal results.
const SLAB_DOWN: f32 = 1.0 - 1.0 / (1u32 << 20) as f32;
const SLAB_UP: f32 = 1.0 + 1.0 / (1u32 << 20) as f32;
const SLAB_ABS: f32 = 1e-37;
/// Rays whose origin or inverse direction fall outside this range take the f64 slab test.
const F32_SAFE: f64 = 1e30;

impl Bvh {
    pub fn bounds(&self) -> Aabb {
        self.bounds.unwrap_or(Aabb::EMPTY)
    }

    /// Per axis, a bound on the magnitude of every box coordinate of the tree (its f32
    /// boxes included), which scales the f32 slab tests' margins.
    pub fn reach(&self) -> [f64; 3] {
        self.reach
    }

    pub fn depth(&self) -> usize {
        self.depth
    }

    /// The tree with [`Bvh::spans`] filled in (for large trees, where a leaf's data is a
    /// DRAM miss that can be started as early as its node's).
    pub fn with_spans(mut self) -> Bvh {
        let mut spans = vec![[u32::MAX, 0]; self.nodes.len()];
        // Children come after their parent in `nodes`, so one backward pass has every
        // child's span ready before its parent takes the union.
        for n in (0..self.nodes.len()).rev() {
            let node = &self.nodes[n];
            let mut span = [u32::MAX, 0];
            for c in (0..WIDTH).filter(|&c| node.index[c] != NO_CHILD) {
                let [lo, hi] = if node.count[c] > 0 {
                    [node.index[c], node.index[c] + u32::from(node.count[c])]
                } else {
                    debug_assert!(node.index[c] as usize > n, "a child before its parent");
                    spans[node.index[c] as usize]
                };
                span = [span[0].min(lo), span[1].max(hi)];
            }
            spans[n] = span;
        }
        self.spans = spans;
        self
    }

    /// Boxes that together hold every primitive: the children of the root and, where those
    /// are interior, their children (at most `WIDTH`² boxes, f32-rounded outward). An
    /// instance's world box is far tighter as the union of these boxes transformed than as
    /// the transformed root box, whose corners stick out once the instance is rotated.
    pub fn boxes_near_root(&self) -> Vec<Aabb> {
        let Some(root) = self.nodes.first() else {
            return Vec::new();
        };
        let box_of = |node: &Node, c: usize| {
            let b = &node.bounds;
            Aabb {
                min: glam::DVec3::new(b[0][c] as f64, b[2][c] as f64, b[4][c] as f64),
                max: glam::DVec3::new(b[1][c] as f64, b[3][c] as f64, b[5][c] as f64),
            }
        };
        let mut out = Vec::new();
        for c in (0..WIDTH).filter(|&c| root.index[c] != NO_CHILD) {
            if root.count[c] > 0 {
                out.push(box_of(root, c));
                continue;
            }
            let child = &self.nodes[root.index[c] as usize];
            for g in (0..WIDTH).filter(|&g| child.index[g] != NO_CHILD) {
                out.push(box_of(child, g));
            }
        }
        out
    }

    /// Visits every leaf the ray may reach before `*t_max`, nearest child first. `leaf` gets
    /// a primitive range and shrinks `t_max` when it finds a closer hit; returning true stops
    /// the traversal (any-hit queries).
    #[inline(always)]
    pub fn traverse(
        &self,
        ray: &Ray,
        t_max: &mut f64,
        leaf: impl FnMut(std::ops::Range<usize>, &mut f64) -> bool,
    ) -> bool {
        if self.nodes.is_empty() {
            return false;
        }
        match RayF32::new(ray, self.reach) {
            Some(r) => {
                #[cfg(target_arch = "x86_64")]
                if WIDTH.is_multiple_of(8) && std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU has AVX2.
                    return unsafe { self.traverse_avx2::<NEAREST_FIRST>(&r, t_max, leaf) };
                }
                self.traverse_with::<NEAREST_FIRST>(t_max, leaf, |node, _, t_far| {
                    r.hit_below(&node.bounds, t_far)
                })
            }
            None => self.traverse_with::<NEAREST_FIRST>(t_max, leaf, |node, t_max, _| {
                hit_f64(node, ray, t_max)
            }),
        }
    }

    /// Like [`Bvh::traverse`], for any-hit queries: children are visited farthest first. A
    /// shadow ray leaves a surface, and the geometry nearest its origin is mostly that surface,
    /// which it cannot hit; a blocker tends to lie farther on (4% more shadow rays per second
    /// on dragon than node order, and 12% more than nearest first).
    #[inline(always)]
    pub fn traverse_any(
        &self,
        ray: &Ray,
        t_max: &mut f64,
        leaf: impl FnMut(std::ops::Range<usize>, &mut f64) -> bool,
    ) -> bool {
        if self.nodes.is_empty() {
            return false;
        }
        match RayF32::new(ray, self.reach) {
            Some(r) => {
                #[cfg(target_arch = "x86_64")]
                if WIDTH.is_multiple_of(8) && std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU has AVX2.
                    return unsafe { self.traverse_avx2::<FARTHEST_FIRST>(&r, t_max, leaf) };
                }
                self.traverse_with::<FARTHEST_FIRST>(t_max, leaf, |node, _, t_far| {
                    r.hit_below(&node.bounds, t_far)
                })
            }
            None => self.traverse_with::<FARTHEST_FIRST>(t_max, leaf, |node, t_max, _| {
                hit_f64(node, ray, t_max)
            }),
        }
    }

    /// [`Bvh::traverse`] with the f64 slab test at every node: the leaves the ray truly
    /// meets, which every f32 walk must hand it too.
    #[cfg(test)]
    pub(super) fn traverse_f64(
        &self,
        ray: &Ray,
        t_max: &mut f64,
        leaf: impl FnMut(std::ops::Range<usize>, &mut f64) -> bool,
    ) -> bool {
        !self.nodes.is_empty()
            && self.traverse_with::<NEAREST_FIRST>(t_max, leaf, |node, t_max, _| {
                hit_f64(node, ray, t_max)
            })
    }

    /// [`Bvh::traverse_with`] with the f32 box test eight lanes at a time, compiled for
    /// AVX2 together with the caller's leaf test. Same arithmetic per lane as [`RayF32::hit`],
    /// so the same nodes are visited in the same order.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn traverse_avx2<const ORDER: u8>(
        &self,
        r: &RayF32,
        t_max: &mut f64,
        leaf: impl FnMut(std::ops::Range<usize>, &mut f64) -> bool,
    ) -> bool {
        // SAFETY: this function only runs where AVX2 is available.
        self.traverse_with::<ORDER>(t_max, leaf, |node, _, t_far| unsafe {
            r.hit_avx2_below(&node.bounds, t_far)
        })
    }

    /// The traversal loop, given a test that returns a node's hit mask and conservative
    /// (never too large) entry distances, from `t_max` or its f32 bound [`t_limit`]. A node's
    /// leaves are intersected at once (a hit shrinks t_max and culls the rest); then the
    /// interior child first in `ORDER` is visited next and the others pushed so that they pop
    /// in that order.
    ///
    /// Entry distances are compared with that f32 bound, made again only when a leaf has
    /// shrunk `t_max`, rather than each converted to f64 (about 60 instructions a dragon ray).
    /// It lies above `t_max` by at most a millionth, so a box entered between the two is one
    /// that holds no hit below `t_max`, which the leaf tests' own f64 bounds reject: the hits
    /// are the same.
    #[inline(always)]
    fn traverse_with<const ORDER: u8>(
        &self,
        t_max: &mut f64,
        mut leaf: impl FnMut(std::ops::Range<usize>, &mut f64) -> bool,
        hit: impl Fn(&Node, f64, f32) -> (u32, [f32; WIDTH]),
    ) -> bool {
        let mut limit = t_limit(*t_max);
        // Left uninitialised: zeroing it per query cost more than a whole traversal of a
        // ray that misses. Only slots below `top`, all written first, are ever read.
        let mut stack = [const { MaybeUninit::<(u32, f32)>::uninit() }; STACK_DEPTH];
        let mut top = 0;
        let mut index = 0usize;
        loop {
            let node = &self.nodes[index];
            let (mask, dist) = hit(node, *t_max, limit);
            let leaves = mask & leaf_mask(node);
            let mut inner = mask & !leaves;
            let mut m = leaves;
            while m != 0 {
                let c = m.trailing_zeros() as usize;
                m &= m - 1;
                if dist[c] <= limit {
                    let first = node.index[c] as usize;
                    if leaf(first..first + node.count[c] as usize, t_max) {
                        return true;
                    }
                    limit = t_limit(*t_max);
                }
            }
            if inner != 0 {
                let c = inner.trailing_zeros() as usize;
                inner &= inner - 1;
                let mut near = (node.index[c], dist[c]);
                prefetch(&self.nodes, near.0);
                if inner != 0 {
                    // Two or more interior children: push all but the nearest, farthest first.
                    let mut rest = [(0u32, 0f32); WIDTH - 1];
                    let mut n = 0;
                    while inner != 0 {
                        let c = inner.trailing_zeros() as usize;
                        inner &= inner - 1;
                        let mut child = (node.index[c], dist[c]);
                        prefetch(&self.nodes, child.0);
                        if ORDER != NODE_ORDER && farther::<ORDER>(near.1, child.1) {
                            std::mem::swap(&mut child, &mut near);
                        }
                        // Insertion into `rest`, kept last-visited first.
                        let mut i = n;
                        while ORDER != NODE_ORDER
                            && i > 0
                            && farther::<ORDER>(child.1, rest[i - 1].1)
                        {
                            rest[i] = rest[i - 1];
                            i -= 1;
                        }
                        rest[i] = child;
                        n += 1;
                    }
                    for &p in &rest[..n] {
                        stack[top].write(p);
                        top += 1;
                    }
                }
                if near.1 <= limit {
                    index = near.0 as usize;
                    continue;
                }
            }
            // Skip subtrees a hit found since they were pushed has put out of reach.
            loop {
                if top == 0 {
                    return false;
                }
                top -= 1;
                // SAFETY: slot `top` was written by the push that raised `top` above it.
                let (n, entry) = unsafe { stack[top].assume_init() };
                if entry <= limit {
                    index = n as usize;
                    break;
                }
            }
        }
    }
}

/// Child visiting orders of [`Bvh::traverse_with`].
const NODE_ORDER: u8 = 0;
const NEAREST_FIRST: u8 = 1;
const FARTHEST_FIRST: u8 = 2;

/// Whether a child at entry distance `a` is visited after one at `b` in `ORDER`.
#[inline(always)]
fn farther<const ORDER: u8>(a: f32, b: f32) -> bool {
    if ORDER == NEAREST_FIRST {
        a > b
    } else {
        a < b
    }
}

/// The slots of `node` that hold leaves.
#[inline(always)]
fn leaf_mask(node: &Node) -> u32 {
    node.leaves as u32
}

/// Starts fetching the cache lines of `nodes[index]` (a hint: an index out of range is
/// harmless, nothing is read).
#[inline(always)]
#[allow(unused_unsafe)]
fn prefetch(nodes: &[Node], index: u32) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let p = nodes.as_ptr().wrapping_add(index as usize) as *const i8;
        // SAFETY: prefetching never faults, whatever the address.
        unsafe {
            for line in 0..size_of::<Node>().div_ceil(64) {
                _mm_prefetch::<_MM_HINT_T0>(p.wrapping_add(64 * line));
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (nodes, index);
}

/// Per-ray constants of the f32 slab test, which finds each plane's distance with one fused
/// multiply-add, `b·inv + c` (a node visit waits on its chain of operations: the former
/// `(b − o)·inv` and its margins took two more steps).
///
/// `c` is `−o·inv` moved down (near planes) or up (far planes) by a margin that covers every
/// rounding: with u = 2^-24, span = (R + |o|)·|inv| (R bounds the tree's box coordinates on
/// the axis), the f32 inverse is off by u·|b·inv| ≤ u·span, `c`'s own rounding to f32 and
/// the multiply-add's one rounding (two where it is not fused) by about as much again each,
/// so a margin of 8u·span plus a tiny absolute term leaves the near distance below, and the
/// far one above, the exact ones. (`c` is rounded to nearest, inside that margin: rounding
/// it toward a side branches on a value that differs from ray to ray, and those branches
/// mispredicted half the time.)
///
/// The top level's walk (`world::top`) uses the same set-up. The f32 rows hold a fourth,
/// unused lane, so that the vector set-up stores each in one instruction.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct RayF32 {
    /// Row of `Node::bounds` holding the near / far plane on each axis.
    pub(crate) near: [usize; 3],
    pub(crate) far: [usize; 3],
    pub(crate) inv: [f32; 4],
    pub(crate) c_near: [f32; 4],
    pub(crate) c_far: [f32; 4],
}

/// The fused slab test's margin, in units of the ray's span on the axis (see [`RayF32`]).
const SLAB_MARGIN: f64 = 8.0 / (1u64 << 24) as f64;
/// Its absolute part, for subnormal results.
const SLAB_MARGIN_ABS: f64 = 1e-30;
/// Rays whose span on some axis reaches this take the f64 slab test: the margins and slab
/// distances then stay far from f32's overflow.
const F32_SPAN: f64 = 1e30;

/// Per axis, a bound on the magnitude of every box coordinate of a tree whose primitives'
/// bounds are `bounds` (its f32 boxes are rounded outward by at most an f32 unit).
#[inline(always)]
pub(super) fn reach(bounds: &Aabb) -> [f64; 3] {
    let r = bounds.min.abs().max(bounds.max.abs());
    [r.x, r.y, r.z].map(|v| v * (1.0 + 1.0 / (1u32 << 20) as f64) + 1e-30)
}

impl RayF32 {
    /// The set-up for a tree reaching `reach` ([`reach`]), or None where the ray is out of the
    /// f32 test's range. Every mesh entry and every shadow and mirror ray of a course scene
    /// makes one, so the three axes are worked in the lanes of two 128-bit f64 vectors, (x, y)
    /// and (z, unused), with the same operations per lane as the scalar form and so the same
    /// bits (2–3% fewer instructions a spheres.scene or stacks.scene sample). One 256-bit
    /// vector was 1–3% slower (docs/performance.md).
    #[cfg(all(target_arch = "x86_64", target_feature = "avx"))]
    #[inline(always)]
    pub(crate) fn new(ray: &Ray, reach: [f64; 3]) -> Option<RayF32> {
        use std::arch::x86_64::*;
        // SAFETY: AVX is enabled for the whole build (cfg above); the stores write the four
        // lanes of four-element arrays.
        unsafe {
            let (o, inv) = (ray.origin, ray.inv_dir);
            // Two halves: (x, y) and (z, unused); the unused lane passes every check.
            let o = [_mm_setr_pd(o.x, o.y), _mm_setr_pd(o.z, 0.0)];
            let inv = [_mm_setr_pd(inv.x, inv.y), _mm_setr_pd(inv.z, 1.0)];
            let reach = [_mm_setr_pd(reach[0], reach[1]), _mm_setr_pd(reach[2], 0.0)];
            let sign = _mm_set1_pd(-0.0);
            let below = |a, b| _mm_cmplt_pd(a, b);
            let mut ok = 0;
            let mut negative = 0usize;
            let mut c_near = [_mm_setzero_pd(); 2];
            let mut c_far = [_mm_setzero_pd(); 2];
            for h in 0..2 {
                let abs_o = _mm_andnot_pd(sign, o[h]);
                let abs_inv = _mm_andnot_pd(sign, inv[h]);
                let span = _mm_mul_pd(_mm_add_pd(reach[h], abs_o), abs_inv);
                let fine = _mm_and_pd(
                    _mm_and_pd(
                        below(abs_o, _mm_set1_pd(F32_SAFE)),
                        below(abs_inv, _mm_set1_pd(F32_SAFE)),
                    ),
                    _mm_and_pd(
                        below(_mm_set1_pd(1.0 / F32_SAFE), abs_inv),
                        below(span, _mm_set1_pd(F32_SPAN)),
                    ),
                );
                ok |= _mm_movemask_pd(fine) << (2 * h);
                negative |= (_mm_movemask_pd(below(inv[h], _mm_setzero_pd())) as usize) << (2 * h);
                let margin = _mm_add_pd(
                    _mm_mul_pd(_mm_set1_pd(SLAB_MARGIN), span),
                    _mm_set1_pd(SLAB_MARGIN_ABS),
                );
                let offset = _mm_mul_pd(_mm_xor_pd(o[h], sign), inv[h]);
                c_near[h] = _mm_sub_pd(offset, margin);
                c_far[h] = _mm_add_pd(offset, margin);
            }
            if ok != 0b1111 {
                return None;
            }
            let to_f32 = |v: [__m128d; 2]| _mm_movelh_ps(_mm_cvtpd_ps(v[0]), _mm_cvtpd_ps(v[1]));
            let mut r = RayF32::default();
            _mm_storeu_ps(r.inv.as_mut_ptr(), to_f32(inv));
            _mm_storeu_ps(r.c_near.as_mut_ptr(), to_f32(c_near));
            _mm_storeu_ps(r.c_far.as_mut_ptr(), to_f32(c_far));
            for a in 0..3 {
                let n = (negative >> a) & 1;
                r.near[a] = 2 * a + n;
                r.far[a] = 2 * a + 1 - n;
            }
            Some(r)
        }
    }

    /// [`RayF32::new`] where the build has no AVX.
    #[cfg(not(all(target_arch = "x86_64", target_feature = "avx")))]
    #[inline(always)]
    pub(crate) fn new(ray: &Ray, reach: [f64; 3]) -> Option<RayF32> {
        Self::new_scalar(ray, reach)
    }

    /// The set-up axis by axis (with AVX, kept for the test that compares the two).
    #[cfg_attr(all(target_arch = "x86_64", target_feature = "avx"), allow(dead_code))]
    #[inline(always)]
    pub(crate) fn new_scalar(ray: &Ray, reach: [f64; 3]) -> Option<RayF32> {
        let o = ray.origin.to_array();
        let inv = ray.inv_dir.to_array();
        let mut r = RayF32::default();
        let mut ok = true;
        for (a, reach) in reach.into_iter().enumerate() {
            let (o, inv) = (o[a], inv[a]);
            let span = (reach + o.abs()) * inv.abs();
            // `&` rather than `&&`: four compares, no branches.
            ok &= (o.abs() < F32_SAFE)
                & (inv.abs() < F32_SAFE)
                & (inv.abs() > 1.0 / F32_SAFE)
                & (span < F32_SPAN);
            // Rounded to nearest, inside the margin (see `SLAB_MARGIN`).
            let margin = SLAB_MARGIN * span + SLAB_MARGIN_ABS;
            r.c_near[a] = (-o * inv - margin) as f32;
            r.c_far[a] = (-o * inv + margin) as f32;
            let negative = inv < 0.0;
            r.near[a] = 2 * a + negative as usize;
            r.far[a] = 2 * a + 1 - negative as usize;
            r.inv[a] = inv as f32;
        }
        // The vector form's unused lane (origin 0, inverse 1, reach 0).
        r.inv[3] = 1.0;
        r.c_near[3] = -SLAB_MARGIN_ABS as f32;
        r.c_far[3] = SLAB_MARGIN_ABS as f32;
        ok.then_some(r)
    }

    /// Hit mask and conservative entry distances of a node's boxes, four at a time.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    #[allow(unused_unsafe)]
    pub(crate) fn hit(&self, bounds: &Bounds, t_max: f64) -> (u32, [f32; WIDTH]) {
        self.hit_below(bounds, t_limit(t_max))
    }

    /// [`RayF32::hit`] for `t_max` given as its f32 bound [`t_limit`].
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    #[allow(unused_unsafe)]
    pub(crate) fn hit_below(&self, bounds: &Bounds, t_far: f32) -> (u32, [f32; WIDTH]) {
        use std::arch::x86_64::*;
        let mut mask = 0;
        let mut dist = [0f32; WIDTH];
        // SAFETY: SSE is part of the x86_64 baseline (FMA where the build enables it); loads
        // read 16 bytes from rows of `WIDTH` (a multiple of four) f32s at offsets `half`,
        // `half + 4`, ….
        unsafe {
            let b = bounds;
            let t_far = _mm_set1_ps(t_far);
            for half in (0..WIDTH).step_by(4) {
                let plane = |row: usize, inv: f32, c: f32| {
                    let b = _mm_loadu_ps(b[row].as_ptr().add(half));
                    #[cfg(target_feature = "fma")]
                    return _mm_fmadd_ps(b, _mm_set1_ps(inv), _mm_set1_ps(c));
                    #[cfg(not(target_feature = "fma"))]
                    return _mm_add_ps(_mm_mul_ps(b, _mm_set1_ps(inv)), _mm_set1_ps(c));
                };
                let nx = plane(self.near[0], self.inv[0], self.c_near[0]);
                let ny = plane(self.near[1], self.inv[1], self.c_near[1]);
                let nz = plane(self.near[2], self.inv[2], self.c_near[2]);
                let fx = plane(self.far[0], self.inv[0], self.c_far[0]);
                let fy = plane(self.far[1], self.inv[1], self.c_far[1]);
                let fz = plane(self.far[2], self.inv[2], self.c_far[2]);
                let near = _mm_max_ps(_mm_max_ps(nx, ny), _mm_max_ps(nz, _mm_setzero_ps()));
                let far = _mm_min_ps(_mm_min_ps(fx, fy), _mm_min_ps(fz, t_far));
                mask |= (_mm_movemask_ps(_mm_cmple_ps(near, far)) as u32) << half;
                _mm_storeu_ps(dist.as_mut_ptr().add(half), near);
            }
        }
        (mask, dist)
    }

    /// [`RayF32::hit`] eight boxes at a time (`WIDTH` a multiple of eight). Not itself an
    /// AVX2 function but always inlined, so that in [`Bvh::traverse_avx2`] its intrinsics
    /// inline too (an AVX2 function is not inlined into a caller without the feature, and
    /// LLVM declined to inline it into the large traversal loop).
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    #[allow(unused_unsafe)]
    pub(crate) unsafe fn hit_avx2(&self, bounds: &Bounds, t_max: f64) -> (u32, [f32; WIDTH]) {
        // SAFETY: the caller guarantees AVX2.
        unsafe { self.hit_avx2_below(bounds, t_limit(t_max)) }
    }

    /// [`RayF32::hit_avx2`] for `t_max` given as its f32 bound [`t_limit`].
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    #[allow(unused_unsafe)]
    pub(crate) unsafe fn hit_avx2_below(&self, bounds: &Bounds, t_far: f32) -> (u32, [f32; WIDTH]) {
        use std::arch::x86_64::*;
        let mut mask = 0;
        let mut dist = [0f32; WIDTH];
        let b = bounds;
        // SAFETY: the caller guarantees AVX2.
        let t_far = unsafe { _mm256_set1_ps(t_far) };
        for half in (0..WIDTH).step_by(8) {
            // SAFETY: AVX2 (and FMA where the build enables it); 32-byte loads from rows of
            // `WIDTH` (a multiple of eight) f32s at offsets `half`, `half + 8`, ….
            let plane = |row: usize, inv: f32, c: f32| unsafe {
                let b = _mm256_loadu_ps(b[row].as_ptr().add(half));
                #[cfg(target_feature = "fma")]
                return _mm256_fmadd_ps(b, _mm256_set1_ps(inv), _mm256_set1_ps(c));
                #[cfg(not(target_feature = "fma"))]
                return _mm256_add_ps(_mm256_mul_ps(b, _mm256_set1_ps(inv)), _mm256_set1_ps(c));
            };
            let nx = plane(self.near[0], self.inv[0], self.c_near[0]);
            let ny = plane(self.near[1], self.inv[1], self.c_near[1]);
            let nz = plane(self.near[2], self.inv[2], self.c_near[2]);
            let fx = plane(self.far[0], self.inv[0], self.c_far[0]);
            let fy = plane(self.far[1], self.inv[1], self.c_far[1]);
            let fz = plane(self.far[2], self.inv[2], self.c_far[2]);
            // SAFETY: the caller guarantees AVX2; the store writes `dist`'s eight f32s at
            // `half`.
            unsafe {
                let near = _mm256_max_ps(
                    _mm256_max_ps(nx, ny),
                    _mm256_max_ps(nz, _mm256_setzero_ps()),
                );
                let far = _mm256_min_ps(_mm256_min_ps(fx, fy), _mm256_min_ps(fz, t_far));
                mask |= (_mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(near, far)) as u32) << half;
                _mm256_storeu_ps(dist.as_mut_ptr().add(half), near);
            }
        }
        (mask, dist)
    }

    #[cfg(not(target_arch = "x86_64"))]
    #[inline(always)]
    pub(crate) fn hit(&self, bounds: &Bounds, t_max: f64) -> (u32, [f32; WIDTH]) {
        self.hit_below(bounds, t_limit(t_max))
    }

    #[cfg(not(target_arch = "x86_64"))]
    #[inline(always)]
    pub(crate) fn hit_below(&self, bounds: &Bounds, t_far: f32) -> (u32, [f32; WIDTH]) {
        let b = bounds;
        let t_max = t_far;
        let mut mask = 0;
        let mut dist = [0f32; WIDTH];
        for c in 0..WIDTH {
            let mut near = 0f32;
            let mut far = t_max;
            for a in 0..3 {
                let tn = b[self.near[a]][c] * self.inv[a] + self.c_near[a];
                let tf = b[self.far[a]][c] * self.inv[a] + self.c_far[a];
                near = if tn > near { tn } else { near };
                far = if tf < far { tf } else { far };
            }
            if near <= far {
                mask |= 1 << c;
            }
            dist[c] = near;
        }
        (mask, dist)
    }
}

/// An f32 bound not below `t_max`, for the fused slab test (the packet test's margin covers
/// the rounding of [`t_max_f32`] its own way).
#[inline(always)]
pub(crate) fn t_limit(t_max: f64) -> f32 {
    t_max_f32(t_max) * SLAB_UP + SLAB_ABS
}

/// `t_max` as f32; the slab margin covers its rounding.
#[inline(always)]
fn t_max_f32(t_max: f64) -> f32 {
    t_max as f32
}

/// The slab test in f64 against a node's f32 boxes, for rays the f32 test cannot take.
#[inline(always)]
fn hit_f64(node: &Node, ray: &Ray, t_max: f64) -> (u32, [f32; WIDTH]) {
    let b = &node.bounds;
    let mut mask = 0;
    let mut dist = [0f32; WIDTH];
    for c in 0..WIDTH {
        if node.index[c] == NO_CHILD {
            continue;
        }
        let tx0 = (b[0][c] as f64 - ray.origin.x) * ray.inv_dir.x;
        let tx1 = (b[1][c] as f64 - ray.origin.x) * ray.inv_dir.x;
        let ty0 = (b[2][c] as f64 - ray.origin.y) * ray.inv_dir.y;
        let ty1 = (b[3][c] as f64 - ray.origin.y) * ray.inv_dir.y;
        let tz0 = (b[4][c] as f64 - ray.origin.z) * ray.inv_dir.z;
        let tz1 = (b[5][c] as f64 - ray.origin.z) * ray.inv_dir.z;
        let near = tx0.min(tx1).max(ty0.min(ty1)).max(tz0.min(tz1)).max(0.0);
        let far = tx0.max(tx1).min(ty0.max(ty1)).min(tz0.max(tz1)).min(t_max);
        if near <= far {
            mask |= 1 << c;
            dist[c] = round_down(near);
        }
    }
    (mask, dist)
}

/// The largest f32 not above `v`.
#[inline(always)]
pub(super) fn round_down(v: f64) -> f32 {
    let f = v as f32;
    if (f as f64) > v {
        f.next_down()
    } else {
        f
    }
}

/// The smallest f32 not below `v`.
#[inline(always)]
pub(super) fn round_up(v: f64) -> f32 {
    let f = v as f32;
    if (f as f64) < v {
        f.next_up()
    } else {
        f
    }
}

#[cfg(test)]
mod tests {
    use glam::DVec3;

    use super::super::build::{to_f32_box, PADDING};
    use super::*;

    fn boxes(n: usize) -> Vec<Aabb> {
        // A deterministic scatter of small boxes.
        crate::test_rng::boxes(12345, n, 100.0, 0.0, 1.0)
    }

    fn leaves(bvh: &Bvh) -> Vec<([f32; 6], u32, u32)> {
        bvh.nodes
            .iter()
            .flat_map(|n| {
                (0..WIDTH).map(move |c| {
                    let b = n.bounds;
                    let aabb = [b[0][c], b[2][c], b[4][c], b[1][c], b[3][c], b[5][c]];
                    (aabb, n.index[c], u32::from(n.count[c]))
                })
            })
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
    fn aligned_leaves_start_on_block_boundaries_and_skip_padding() {
        let prims = boxes(3000);
        let bvh = Bvh::build_aligned(&prims, 4);
        assert_eq!(bvh.order.len() % 4, 0);
        let mut seen = vec![0; prims.len()];
        let mut slots = 0;
        for (_, first, count) in leaves(&bvh) {
            assert_eq!(first % 4, 0);
            for slot in first..first + count {
                seen[bvh.order[slot as usize] as usize] += 1;
            }
            slots += count.next_multiple_of(4);
        }
        assert!(seen.iter().all(|&s| s == 1));
        assert_eq!(slots as usize, bvh.order.len());
        let padding = bvh.order.iter().filter(|&&o| o == PADDING).count();
        assert_eq!(padding + prims.len(), bvh.order.len());
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
            let mut found_any = Vec::new();
            bvh.traverse_any(&ray, &mut f64::INFINITY.clone(), |range, _| {
                for slot in range {
                    let p = bvh.order[slot] as usize;
                    if prims[p].hit(&ray, f64::INFINITY).is_some() {
                        found_any.push(p);
                    }
                }
                false
            });
            expected.sort();
            found.sort();
            found_any.sort();
            assert_eq!(found, expected);
            assert_eq!(found_any, expected);
        }
    }

    /// A closest-hit walk whose leaf test shrinks `t_max` at each hit (culling what lies
    /// beyond) finds the box brute force finds first, the lowest index among equally near
    /// ones, from inside and outside the scatter.
    #[test]
    fn the_closest_hit_walk_finds_the_nearest_box() {
        // Boxes large enough to overlap, so that a ray meets several in most subtrees.
        let prims = crate::test_rng::boxes(77, 3000, 100.0, 0.0, 6.0);
        let mut next = crate::test_rng::uniform(78);
        let bvh = Bvh::build(&prims);
        for _ in 0..2000 {
            let origin = DVec3::new(next(), next(), next()) * 160.0 - 30.0;
            // Aimed at a box's centre, so every ray hits something.
            let target = prims[(next() * prims.len() as f64) as usize].centroid();
            let dir = (target - origin).normalize();
            let ray = Ray::new(origin, dir);
            let nearest = |best: Option<(f64, usize)>, (t, p): (f64, usize)| match best {
                Some(b) if (b.0, b.1) <= (t, p) => Some(b),
                _ => Some((t, p)),
            };
            let expected = (0..prims.len())
                .filter_map(|p| Some((prims[p].hit(&ray, f64::INFINITY)?, p)))
                .fold(None, nearest);
            let mut found = None;
            let mut t_max = f64::INFINITY;
            bvh.traverse(&ray, &mut t_max, |range, t_max| {
                for slot in range {
                    let p = bvh.order[slot] as usize;
                    if let Some(t) = prims[p].hit(&ray, *t_max) {
                        found = nearest(found, (t, p));
                        *t_max = t;
                    }
                }
                false
            });
            assert!(expected.is_some());
            assert_eq!(found, expected, "ray from {origin} along {dir}");
        }
    }

    /// The vector ray set-up gives the scalar one's fields bit for bit, and refuses the same
    /// rays (huge origins, near-axis directions whose inverse overflows the f32 range).
    #[cfg(all(target_arch = "x86_64", target_feature = "avx"))]
    #[test]
    fn the_vector_ray_set_up_is_the_scalar_one() {
        let mut next = crate::test_rng::uniform(11);
        let mut refused = 0;
        for i in 0..20_000 {
            let scale = 10f64.powf(next() * 70.0 - 35.0);
            let origin = DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5) * scale;
            let mut dir = DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5);
            match i % 7 {
                0 => dir.x = 0.0,
                1 => dir.y = -0.0,
                2 => dir.z = 1e-32 * (next() - 0.5),
                _ => {}
            }
            let ray = Ray::new(origin, dir);
            let reach = [next(), next(), next()].map(|v| v * 10f64.powf(next() * 60.0 - 30.0));
            let vector = RayF32::new(&ray, reach);
            let scalar = RayF32::new_scalar(&ray, reach);
            let bits = |r: &Option<RayF32>| {
                r.as_ref().map(|r| {
                    let f = |v: [f32; 4]| v.map(f32::to_bits);
                    (r.near, r.far, f(r.inv), f(r.c_near), f(r.c_far))
                })
            };
            assert_eq!(
                bits(&vector),
                bits(&scalar),
                "ray {i}: {ray:?}, reach {reach:?}"
            );
            refused += vector.is_none() as usize;
        }
        // Both kinds of ray are checked.
        assert!((2_000..18_000).contains(&refused), "{refused} refused");
    }

    #[test]
    fn f32_traversal_never_culls_a_box_hit_at_any_scale() {
        let mut next = crate::test_rng::uniform(987654321);
        for (scale, offset) in [
            (1e-4, 0.0),
            (1e-4, 3.7),
            (1.0, -2.0),
            (1e5, 1e5),
            (0.01, 1e4),
        ] {
            let prims: Vec<Aabb> = (0..500)
                .map(|_| {
                    let c = DVec3::new(next(), next(), next()) * 10.0 * scale + offset;
                    let e = DVec3::new(next(), next(), next()) * 0.3 * scale;
                    Aabb {
                        min: c - e,
                        max: c + e,
                    }
                })
                .collect();
            let bvh = Bvh::build(&prims);
            for i in 0..400 {
                // Aim at a corner, an edge or a face point of some box, from near and far.
                let target = prims[i % prims.len()];
                let pick = |k: f64, a: f64, b: f64| {
                    if k < 0.33 {
                        a
                    } else if k < 0.66 {
                        b
                    } else {
                        a + (b - a) * k
                    }
                };
                let aim = DVec3::new(
                    pick(next(), target.min.x, target.max.x),
                    pick(next(), target.min.y, target.max.y),
                    pick(next(), target.min.z, target.max.z),
                );
                let dist = scale * 10f64.powf(next() * 4.0 - 1.0);
                let mut dir = DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5).normalize();
                if i % 7 == 0 {
                    dir.x = 0.0; // axis-parallel rays take the f64 test
                }
                let origin = aim - dir * dist;
                let ray = Ray::new(origin, dir);
                let t_max = if i % 2 == 0 { f64::INFINITY } else { dist };
                let expected: Vec<usize> = (0..prims.len())
                    .filter(|&p| prims[p].hit(&ray, t_max).is_some())
                    .collect();
                let mut found = vec![false; prims.len()];
                let mut limit = t_max;
                bvh.traverse(&ray, &mut limit, |range, _| {
                    for slot in range {
                        found[bvh.order[slot] as usize] = true;
                    }
                    false
                });
                for p in expected {
                    assert!(found[p], "scale {scale}: box {p} culled for ray {i}");
                }
            }
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_box_test_matches_the_sse_one() {
        if !std::arch::is_x86_feature_detected!("avx2") {
            return;
        }
        let bvh = Bvh::build(&boxes(3000));
        let mut next = crate::test_rng::uniform(42);
        let mut hits = 0;
        for i in 0..2000 {
            let origin = DVec3::new(next(), next(), next()) * 140.0 - 20.0;
            let dir = DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5).normalize();
            let r = RayF32::new(&Ray::new(origin, dir), bvh.reach).expect("an f32-safe ray");
            let t_max = if i % 2 == 0 { f64::INFINITY } else { 30.0 };
            for node in &bvh.nodes {
                let sse = r.hit(&node.bounds, t_max);
                // SAFETY: AVX2 was detected above.
                let avx = unsafe { r.hit_avx2(&node.bounds, t_max) };
                assert_eq!(sse.0, avx.0);
                for c in 0..WIDTH {
                    if sse.0 & (1 << c) != 0 {
                        assert_eq!(sse.1[c].to_bits(), avx.1[c].to_bits());
                    }
                }
                hits += sse.0.count_ones();
            }
        }
        assert!(hits > 1000, "{hits} box hits");
    }

    #[test]
    fn spans_cover_exactly_the_leaves_below_each_node() {
        let bvh = Bvh::build_aligned(&boxes(5000), 4).with_spans();
        assert_eq!(bvh.spans.len(), bvh.nodes.len());
        // The slots of the leaves below `n`, by walking the subtree.
        fn below(bvh: &Bvh, n: usize, out: &mut Vec<u32>) {
            let node = &bvh.nodes[n];
            for c in (0..WIDTH).filter(|&c| node.index[c] != NO_CHILD) {
                if node.count[c] > 0 {
                    out.extend(node.index[c]..node.index[c] + u32::from(node.count[c]));
                } else {
                    below(bvh, node.index[c] as usize, out);
                }
            }
        }
        for n in 0..bvh.nodes.len() {
            let mut slots = Vec::new();
            below(&bvh, n, &mut slots);
            let lo = *slots.iter().min().unwrap();
            let hi = *slots.iter().max().unwrap() + 1;
            assert_eq!(bvh.spans[n], [lo, hi], "node {n}");
        }
        assert_eq!(bvh.spans[0], [0, bvh.order.len() as u32]);
        assert!(Bvh::build(&[]).with_spans().spans.is_empty());
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
    fn boxes_near_the_root_hold_every_primitive() {
        let prims = boxes(3000);
        let bvh = Bvh::build_aligned(&prims, 4);
        let near = bvh.boxes_near_root();
        assert!(
            near.len() > WIDTH && near.len() <= WIDTH * WIDTH,
            "{}",
            near.len()
        );
        for p in &prims {
            assert!(near
                .iter()
                .any(|b| b.min.cmple(p.min).all() && b.max.cmpge(p.max).all()));
        }
        assert!(Bvh::build(&[]).boxes_near_root().is_empty());
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
