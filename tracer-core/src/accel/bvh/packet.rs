//! Packet traversal: up to [`PACKET`] coherent rays (a block of eye rays) walk the tree
//! together. Each interior node is tested once for the whole packet with interval bounds of
//! the rays (every ray's origin and inverse direction lie in a box), so the upper levels cost
//! one node test per packet instead of one per ray; only at a node with leaf children, where
//! the packet's paths part, or (in a large tree) where one ray is left does each ray take its
//! own box test, the single-ray traversal's.
//!
//! The packet test is conservative: it culls a box only when no ray of the packet can enter
//! it before the packet's farthest `t_max`, so every ray meets at least the leaves the
//! single-ray traversal would hand it (the owner's nearest-hit rule must not depend on the
//! order they come in).

use std::mem::MaybeUninit;
use std::ops::Range;

use super::{
    farther, leaf_mask, prefetch, round_down, round_up, t_max_f32, Bvh, Fetch, Node, RayF32,
    F32_SAFE, F32_SPAN, FARTHEST_FIRST, NEAREST_FIRST, NO_CHILD, SLAB_ABS, SLAB_DOWN, SLAB_UP,
    STACK_DEPTH, SUBTREE_FETCH_SLOTS, WIDTH,
};
use glam::DVec3;

use crate::geometry::{Aabb, Ray};

/// The most rays [`Bvh::traverse_packet`] takes at once (one bit each in a `u64`).
pub const PACKET: usize = 64;

/// Interval bounds of a packet of rays, per axis: an f32 range holding every ray's origin
/// (rounded outward) and one holding every ray's inverse direction (rounded outward).
#[derive(Clone, Copy, Debug)]
pub struct PacketBounds {
    /// Row of `Node::bounds` holding the near / far plane on each axis (by the sign the
    /// rays' directions share there).
    near: [usize; 3],
    far: [usize; 3],
    o_lo: [f32; 3],
    o_hi: [f32; 3],
    inv_lo: [f32; 3],
    inv_hi: [f32; 3],
    /// Per axis, the end of the origins' range that gives the smallest entry distance
    /// (`o_hi` where the directions are positive, `o_lo` where negative), and the one that
    /// gives the largest exit distance: with the directions' sign known, two of the four
    /// products of interval ends are never the extreme ones (see [`PacketBounds::slab`]).
    o_enter: [f32; 3],
    o_exit: [f32; 3],
    /// Axes along which the directions differ in sign: they bound nothing (a lower bound of
    /// 0 on entry, none on exit), which keeps the test conservative.
    mixed: [bool; 3],
}

impl PacketBounds {
    /// The bounds of `rays`, or None when there are none or one is outside the f32 test's
    /// range (those take the single-ray traversal, which falls back to f64).
    pub fn new(rays: &[Ray]) -> Option<PacketBounds> {
        if rays.is_empty() {
            return None;
        }
        let mut p = PacketBounds {
            near: [0; 3],
            far: [0; 3],
            o_lo: [0.0; 3],
            o_hi: [0.0; 3],
            inv_lo: [0.0; 3],
            inv_hi: [0.0; 3],
            o_enter: [0.0; 3],
            o_exit: [0.0; 3],
            mixed: [false; 3],
        };
        // One pass over the rays with plain comparisons (`f64::min` handles NaN at a few
        // instructions more per lane, and this runs for every packet and object).
        let lt = |a: DVec3, b: DVec3| DVec3::select(a.cmplt(b), a, b);
        let gt = |a: DVec3, b: DVec3| DVec3::select(a.cmpgt(b), a, b);
        let first = &rays[0];
        let (mut o_lo, mut o_hi) = (first.origin, first.origin);
        let (mut i_lo, mut i_hi) = (first.inv_dir, first.inv_dir);
        let mut small = first.inv_dir.abs();
        // A NaN or infinity anywhere makes this sum non-finite (and so does a sum past
        // f64's range, of values the range check below refuses anyway).
        let mut sum = DVec3::ZERO;
        for r in rays {
            o_lo = lt(r.origin, o_lo);
            o_hi = gt(r.origin, o_hi);
            i_lo = lt(r.inv_dir, i_lo);
            i_hi = gt(r.inv_dir, i_hi);
            small = lt(r.inv_dir.abs(), small);
            sum += r.origin + r.inv_dir;
        }
        let finite = sum.is_finite();
        for a in 0..3 {
            // The same range as `RayF32::new`'s, so that every ray of a packet also has its
            // f32 single-ray set-up.
            let big = o_hi[a].max(-o_lo[a]) < F32_SAFE && i_hi[a].max(-i_lo[a]) < F32_SAFE;
            if !(finite && big && small[a] > 1.0 / F32_SAFE) {
                return None;
            }
            p.o_lo[a] = round_down(o_lo[a]);
            p.o_hi[a] = round_up(o_hi[a]);
            p.inv_lo[a] = round_down(i_lo[a]);
            p.inv_hi[a] = round_up(i_hi[a]);
            if i_lo[a] > 0.0 {
                (p.near[a], p.far[a]) = (2 * a, 2 * a + 1);
                (p.o_enter[a], p.o_exit[a]) = (p.o_hi[a], p.o_lo[a]);
            } else if i_hi[a] < 0.0 {
                (p.near[a], p.far[a]) = (2 * a + 1, 2 * a);
                (p.o_enter[a], p.o_exit[a]) = (p.o_lo[a], p.o_hi[a]);
            } else {
                p.mixed[a] = true;
            }
        }
        Some(p)
    }

    /// Whether every ray of the packet is in range of the single-ray f32 test for a tree
    /// reaching `reach` ([`reach`]): the packet's paths part into single rays, which must
    /// then all have their f32 set-up.
    fn spans_fit(&self, reach: [f64; 3]) -> bool {
        (0..3).all(|a| {
            let o = (self.o_lo[a] as f64).abs().max((self.o_hi[a] as f64).abs());
            let inv = (self.inv_lo[a] as f64)
                .abs()
                .max((self.inv_hi[a] as f64).abs());
            (reach[a] + o) * inv < F32_SPAN
        })
    }

    /// Hit mask and entry distances (lower bounds over the packet) of a node's boxes: a
    /// child is out of the mask only if no ray of the packet can enter it before `t_max`.
    /// Per lane and axis, the slab distances of the box's near and far planes are bounded by
    /// the four products of the interval ends (exact f32 ends, so one rounding per operation,
    /// far inside the single-ray test's 16-unit margin, which is applied the same way).
    #[inline(always)]
    fn hit(&self, node: &Node, t_max: f32) -> (u32, [f32; WIDTH]) {
        let b = &node.bounds;
        let mut mask = 0;
        let mut dist = [0f32; WIDTH];
        for c in 0..WIDTH {
            let mut near = 0f32;
            let mut far = t_max;
            for a in 0..3 {
                if self.mixed[a] {
                    continue;
                }
                let (tn, tf) = self.slab(a, b[self.near[a]][c], b[self.far[a]][c]);
                near = near.max(tn);
                far = far.min(tf);
            }
            let near = near * SLAB_DOWN;
            let far = far * SLAB_UP + SLAB_ABS;
            if near <= far {
                mask |= 1 << c;
            }
            dist[c] = near;
        }
        (mask & used_mask(node), dist)
    }

    /// [`PacketBounds::hit`] eight boxes at a time, the same operations lane by lane (no
    /// NaN reaches a used lane: mixed axes, whose inverse directions straddle zero, are
    /// skipped, and unused lanes are masked off), so the same bits.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    #[allow(unused_unsafe)]
    unsafe fn hit_avx2(&self, node: &Node, t_max: f32) -> (u32, [f32; WIDTH]) {
        use std::arch::x86_64::*;
        let b = &node.bounds;
        let mut mask = 0;
        let mut dist = [0f32; WIDTH];
        // SAFETY: the caller guarantees AVX2; loads read rows of `WIDTH` (a multiple of
        // eight) f32s at offsets `half`, `half + 8`, …; the store writes eight of `dist`'s.
        unsafe {
            for half in (0..WIDTH).step_by(8) {
                let mut near = _mm256_setzero_ps();
                let mut far = _mm256_set1_ps(t_max);
                for a in 0..3 {
                    if self.mixed[a] {
                        continue;
                    }
                    let (i0, i1) = (
                        _mm256_set1_ps(self.inv_lo[a]),
                        _mm256_set1_ps(self.inv_hi[a]),
                    );
                    let bn = _mm256_loadu_ps(b[self.near[a]].as_ptr().add(half));
                    let bf = _mm256_loadu_ps(b[self.far[a]].as_ptr().add(half));
                    let n = _mm256_sub_ps(bn, _mm256_set1_ps(self.o_enter[a]));
                    let f = _mm256_sub_ps(bf, _mm256_set1_ps(self.o_exit[a]));
                    let tn = _mm256_min_ps(_mm256_mul_ps(n, i0), _mm256_mul_ps(n, i1));
                    let tf = _mm256_max_ps(_mm256_mul_ps(f, i0), _mm256_mul_ps(f, i1));
                    near = _mm256_max_ps(near, tn);
                    far = _mm256_min_ps(far, tf);
                }
                let near = _mm256_mul_ps(near, _mm256_set1_ps(SLAB_DOWN));
                let far = _mm256_add_ps(
                    _mm256_mul_ps(far, _mm256_set1_ps(SLAB_UP)),
                    _mm256_set1_ps(SLAB_ABS),
                );
                mask |= (_mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(near, far)) as u32) << half;
                _mm256_storeu_ps(dist.as_mut_ptr().add(half), near);
            }
        }
        (mask & used_mask(node), dist)
    }

    /// Whether some ray of the packet may enter `aabb` before `t_max` (conservative, like
    /// the node test): lets a caller skip a whole object for a packet that misses its box.
    pub fn may_hit(&self, aabb: &Aabb, t_max: f64) -> bool {
        let mut bounds = [0f32; 6];
        for a in 0..3 {
            bounds[2 * a] = round_down(aabb.min[a]);
            bounds[2 * a + 1] = round_up(aabb.max[a]);
        }
        let mut near = 0f32;
        let mut far = t_max_f32(t_max);
        for a in 0..3 {
            if self.mixed[a] {
                continue;
            }
            let (tn, tf) = self.slab(a, bounds[self.near[a]], bounds[self.far[a]]);
            near = near.max(tn);
            far = far.min(tf);
        }
        near * SLAB_DOWN <= far * SLAB_UP + SLAB_ABS
    }

    /// Lower bound of entry and upper bound of exit over the packet for the planes at
    /// `near` and `far` on axis `a` (not mixed), as [`PacketBounds::hit`] bounds them.
    ///
    /// Of the four products of the interval ends (plane − origin) × inverse direction, the
    /// smallest comes from the origin end `o_enter`: with every inverse direction of one sign,
    /// the product moves monotonically with the origin, and rounding keeps that order. So only
    /// that end's two products are made, and likewise `o_exit`'s for the exit: the bounds all
    /// four gave, at half the operations.
    #[inline(always)]
    fn slab(&self, a: usize, near: f32, far: f32) -> (f32, f32) {
        let (i0, i1) = (self.inv_lo[a], self.inv_hi[a]);
        let n = near - self.o_enter[a];
        let f = far - self.o_exit[a];
        ((n * i0).min(n * i1), (f * i0).max(f * i1))
    }
}

/// The slots of `node` that hold a child.
#[inline(always)]
fn used_mask(node: &Node) -> u32 {
    let mut mask = 0;
    for c in 0..WIDTH {
        mask |= ((node.index[c] != NO_CHILD) as u32) << c;
    }
    mask
}

/// How far a packet's rays part, which decides how the packet walk hands them leaves
/// ([`Bvh::traverse_packet`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Spread {
    /// Rays that part ways (an 8×8 block of pixels' eye rays): where the packet's paths may
    /// part, each ray tests the node's boxes itself and goes only where it meets one.
    Wide,
    /// Rays within one pixel's footprint (its samples' eye rays): nearly every leaf the packet
    /// reaches is one each ray reaches, so each ray is handed every leaf the packet's own
    /// test passes, without box tests or a set-up of its own. (With the rays' own tests, a
    /// pixel packet's walk in toy.scene's mesh cost its render about 4%; a block of 8×8
    /// pixels handed every leaf ran 2.5× slower.)
    Pixel,
}

impl Bvh {
    /// Hands `leaf(i, primitives, t_max)` every leaf ray `rays[i]` may reach before its
    /// `t_max[i]` (which `leaf` shrinks as it finds closer hits): at least the leaves
    /// [`Bvh::traverse`] hands that ray, but in another order and possibly more, so the
    /// owner's rule for the nearest hit must not depend on the order (ties at equal t broken
    /// by primitive slot, say). At most [`PACKET`] rays; rays the f32 tests cannot take
    /// make the whole packet go ray by ray.
    ///
    /// `fetch(primitives, what)` is a hint: at a node with leaf children every ray's leaves
    /// are named to it ([`Fetch::Leaf`]) before any is handed to `leaf`, so the owner can
    /// start loading them all (in a large mesh each is a DRAM miss, and loaded one after
    /// another they add up); where the tree has [`Bvh::spans`], a small subtree's leaves are
    /// named ([`Fetch::Subtree`]) as its node is fetched, before the packet reaches it. A
    /// packet that goes ray by ray (see above) names nothing.
    ///
    /// `spread` says how the rays part ([`Spread`]): it changes which extra leaves a ray is
    /// handed, never a leaf it needs.
    #[inline(always)]
    pub fn traverse_packet(
        &self,
        rays: &[Ray],
        t_max: &mut [f64],
        spread: Spread,
        fetch: impl Fn(Range<usize>, Fetch),
        mut leaf: impl FnMut(usize, Range<usize>, &mut f64),
    ) {
        self.packet::<NEAREST_FIRST>(rays, t_max, spread, fetch, |i, range, t| {
            leaf(i, range, t);
            false
        });
    }

    /// The any-hit counterpart of [`Bvh::traverse_packet`], as [`Bvh::traverse_any`] is of
    /// [`Bvh::traverse`]: `leaf(i, primitives, t_max)` returns true when it finds a hit for
    /// ray `i`, which then leaves the packet (its `t_max[i]` becomes −∞), and the walk ends
    /// when every ray has. Children are visited farthest first by the packet's entry bound.
    /// Returns the mask of the rays `leaf` found a hit for; every other ray was handed at
    /// least the leaves `traverse_any` would hand it, so the answers are the same.
    /// `fetch` as for [`Bvh::traverse_packet`].
    #[inline(always)]
    pub fn traverse_packet_any(
        &self,
        rays: &[Ray],
        t_max: &mut [f64],
        fetch: impl Fn(Range<usize>, Fetch),
        leaf: impl FnMut(usize, Range<usize>, &mut f64) -> bool,
    ) -> u64 {
        self.packet::<FARTHEST_FIRST>(rays, t_max, Spread::Wide, fetch, leaf)
    }

    /// [`Bvh::traverse_packet`] or [`Bvh::traverse_packet_any`] by `ORDER`; returns the rays
    /// for which `leaf` returned true.
    #[inline(always)]
    fn packet<const ORDER: u8>(
        &self,
        rays: &[Ray],
        t_max: &mut [f64],
        spread: Spread,
        fetch: impl Fn(Range<usize>, Fetch),
        mut leaf: impl FnMut(usize, Range<usize>, &mut f64) -> bool,
    ) -> u64 {
        assert!(rays.len() <= PACKET && t_max.len() == rays.len());
        if self.nodes.is_empty() || rays.is_empty() {
            return 0;
        }
        let Some(packet) = PacketBounds::new(rays).filter(|p| p.spans_fit(self.reach)) else {
            let mut found = 0;
            for (i, ray) in rays.iter().enumerate() {
                let leaf = |range, t: &mut f64| leaf(i, range, t);
                let hit = if ORDER == FARTHEST_FIRST {
                    self.traverse_any(ray, &mut t_max[i], leaf)
                } else {
                    self.traverse(ray, &mut t_max[i], leaf)
                };
                if hit {
                    found |= 1 << i;
                    t_max[i] = f64::NEG_INFINITY;
                }
            }
            return found;
        };
        let all = u64::MAX >> (64 - rays.len());
        #[cfg(target_arch = "x86_64")]
        if WIDTH.is_multiple_of(8) && std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2.
            return all
                & !unsafe {
                    self.traverse_packet_avx2::<ORDER>(&packet, rays, t_max, spread, fetch, leaf)
                };
        }
        all & !self.traverse_packet_with::<ORDER>(
            rays,
            t_max,
            spread,
            fetch,
            leaf,
            |node, far| packet.hit(node, far),
            |r, node, t_max| r.hit(&node.bounds, t_max),
        )
    }

    /// [`Bvh::traverse_packet_with`] compiled for AVX2 with the owner's leaf test, both box
    /// tests eight lanes at a time (the same bits as the SSE ones).
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn traverse_packet_avx2<const ORDER: u8>(
        &self,
        packet: &PacketBounds,
        rays: &[Ray],
        t_max: &mut [f64],
        spread: Spread,
        fetch: impl Fn(Range<usize>, Fetch),
        leaf: impl FnMut(usize, Range<usize>, &mut f64) -> bool,
    ) -> u64 {
        // SAFETY: this function only runs where AVX2 is available.
        self.traverse_packet_with::<ORDER>(
            rays,
            t_max,
            spread,
            fetch,
            leaf,
            |node, far| unsafe { packet.hit_avx2(node, far) },
            |r, node, t_max| unsafe { r.hit_avx2(&node.bounds, t_max) },
        )
    }

    /// Hands `leaf(slots, t_max)` every leaf some ray of a packet with bounds `packet` may
    /// reach before its `t_max[i]` (which `leaf` shrinks), nearest first by the packet's
    /// lower bound of entry; the packet test alone decides (for a level of few, large
    /// leaves, such as the top level over objects, where the owner tests each ray itself).
    pub fn traverse_packet_leaves(
        &self,
        packet: &PacketBounds,
        t_max: &mut [f64],
        mut leaf: impl FnMut(Range<usize>, &mut [f64]),
    ) {
        self.packet_leaves::<NEAREST_FIRST>(packet, t_max, |range, t_max, _| leaf(range, t_max));
    }

    /// [`Bvh::traverse_packet_leaves`] for any-hit queries, farthest first: `leaf(slots,
    /// t_max, live)` tests the rays in `live` (at first all of `t_max`'s) and clears the bit
    /// of each ray it finds a hit for; such a ray's `t_max` becomes −∞, and the walk ends
    /// when no ray is left. Returns the rays left.
    pub fn traverse_packet_leaves_any(
        &self,
        packet: &PacketBounds,
        t_max: &mut [f64],
        leaf: impl FnMut(Range<usize>, &mut [f64], &mut u64),
    ) -> u64 {
        self.packet_leaves::<FARTHEST_FIRST>(packet, t_max, leaf)
    }

    #[inline(always)]
    fn packet_leaves<const ORDER: u8>(
        &self,
        packet: &PacketBounds,
        t_max: &mut [f64],
        mut leaf: impl FnMut(Range<usize>, &mut [f64], &mut u64),
    ) -> u64 {
        let all = u64::MAX >> (64 - t_max.len().clamp(1, 64));
        if self.nodes.is_empty() || t_max.is_empty() {
            return all;
        }
        self.packet_walk::<ORDER, ()>(
            &mut (),
            t_max,
            all,
            |node, far| packet.hit(node, far),
            |_, _, _, _| None,
            |_, node, leaves, _, _, dist, t_max, live| {
                // Closest-hit walks take a node's leaves nearest first by the packet's entry
                // bound: over instances, a near one's hits then keep its rays out of the
                // farther ones (see `World::object_packet`).
                let mut order = [0u8; WIDTH];
                let mut n = 0;
                let mut m = leaves;
                while m != 0 {
                    let c = m.trailing_zeros() as u8;
                    m &= m - 1;
                    let mut i = n;
                    while ORDER == NEAREST_FIRST
                        && i > 0
                        && dist[order[i - 1] as usize] > dist[c as usize]
                    {
                        order[i] = order[i - 1];
                        i -= 1;
                    }
                    order[i] = c;
                    n += 1;
                }
                for &c in &order[..n] {
                    if *live == 0 {
                        break;
                    }
                    let c = c as usize;
                    let first = node.index[c] as usize;
                    leaf(first..first + node.count[c] as usize, t_max, live);
                }
                None
            },
            |_| {},
        )
    }

    /// The walk of [`Bvh::traverse_packet`] (`ORDER` nearest first) and
    /// [`Bvh::traverse_packet_any`] (farthest first). Each ray takes its own box test (the
    /// single-ray traversal's) only where the packet's paths part: at a node with leaf
    /// children (to pick its leaves) and where two or more interior children are entered (to
    /// split the packet's rays among them); elsewhere the packet test alone passes the rays
    /// down. A ray for which `leaf` returns true leaves the packet; returns the rays left.
    /// With [`Spread::Pixel`] no ray takes a test of its own: each is handed the leaves the
    /// packet test passes, and every ray enters every child the packet enters.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn traverse_packet_with<const ORDER: u8>(
        &self,
        rays: &[Ray],
        t_max: &mut [f64],
        spread: Spread,
        fetch: impl Fn(Range<usize>, Fetch),
        mut leaf: impl FnMut(usize, Range<usize>, &mut f64) -> bool,
        packet_hit: impl Fn(&Node, f32) -> (u32, [f32; WIDTH]),
        ray_hit: impl Fn(&RayF32, &Node, f64) -> (u32, [f32; WIDTH]),
    ) -> u64 {
        // Each ray's f32 set-up, made when the packet's paths first part (a packet that
        // misses everything never pays for it).
        let mut singles = Singles {
            rays: [const { MaybeUninit::<RayF32>::uninit() }; PACKET],
            ready: false,
            reach: self.reach,
        };
        // The rays that reach leaves at a node, with their leaf masks and entry distances:
        // all are fetched before the first is tested. Only the first `reach` are written.
        let mut reached = [const { MaybeUninit::<(u8, u32, [f32; WIDTH])>::uninit() }; PACKET];
        let all = u64::MAX >> (64 - rays.len());
        self.packet_walk::<ORDER, Singles>(
            &mut singles,
            t_max,
            all,
            packet_hit,
            // Only in a large tree (one with spans): the packet's bounds would send a lone ray
            // into every subtree the whole packet may reach (on a 10 M-triangle mesh, 13% of
            // the walk's node visits, each a cache miss). In a cached tree those visits cost
            // little, and the dragon ran 1-2% slower with the own test everywhere.
            |singles, i, node, t_max| {
                (!self.spans.is_empty()).then(|| ray_hit(singles.get(rays, i), node, t_max))
            },
            |singles, node, leaves, inner, active, packet_dist, t_max, live| {
                if spread == Spread::Pixel {
                    hand_packet_leaves(
                        node,
                        leaves,
                        active,
                        packet_dist,
                        t_max,
                        live,
                        &fetch,
                        &mut leaf,
                    );
                    return None;
                }
                let single = singles.all(rays);
                let mut split = [0u64; WIDTH];
                let mut reach = 0;
                let mut a = active;
                while a != 0 {
                    let i = a.trailing_zeros() as usize;
                    a &= a - 1;
                    // SAFETY: `all` wrote the first `rays.len()` entries; `active` names no others.
                    let r = unsafe { single[i].assume_init_ref() };
                    let (m, d) = ray_hit(r, node, t_max[i]);
                    let mut l = m & leaves;
                    if l != 0 {
                        while l != 0 {
                            let c = l.trailing_zeros() as usize;
                            l &= l - 1;
                            if d[c] as f64 <= t_max[i] {
                                let first = node.index[c] as usize;
                                fetch(first..first + node.count[c] as usize, Fetch::Leaf);
                            }
                        }
                        reached[reach].write((i as u8, m & leaves, d));
                        reach += 1;
                    }
                    let mut n = m & inner;
                    while n != 0 {
                        let c = n.trailing_zeros() as usize;
                        n &= n - 1;
                        split[c] |= 1 << i;
                    }
                }
                for entry in &reached[..reach] {
                    // SAFETY: the first `reach` entries were written above.
                    let (i, mut l, d) = unsafe { entry.assume_init_read() };
                    let i = i as usize;
                    while l != 0 {
                        let c = l.trailing_zeros() as usize;
                        l &= l - 1;
                        if d[c] as f64 <= t_max[i] {
                            let first = node.index[c] as usize;
                            if leaf(i, first..first + node.count[c] as usize, &mut t_max[i]) {
                                *live &= !(1 << i);
                                break;
                            }
                        }
                    }
                }
                // A ray that found its hit (any-hit) enters no child.
                for s in &mut split {
                    *s &= *live;
                }
                Some(split)
            },
            |child| {
                if let Some(&[lo, hi]) = self.spans.get(child as usize) {
                    if hi > lo && hi - lo <= SUBTREE_FETCH_SLOTS {
                        fetch(lo as usize..hi as usize, Fetch::Subtree);
                    }
                }
            },
        )
    }

    /// The packet walk over interior nodes, in `ORDER` by the packet's lower bound of entry,
    /// each node carrying the mask of the packet's rays that may enter it. A node reached by
    /// one ray alone is tested with `ray_hit(state, ray, node, t_max)`, that ray's own test,
    /// where the owner gives one (else with the packet's, `packet_hit`).
    /// `per_ray(state, node, leaves, inner, rays, dist, t_max, live)` is called where the
    /// packet enters leaf children (`leaves`) or two or more interior ones (`inner`) and `rays`
    /// holds more than one ray (`dist`: the node test's entry bounds); it handles the leaves, may clear rays that are done from `live` (any-hit
    /// queries: their `t_max` is set to −∞ and they are dropped from every pending subtree),
    /// and may return, per child, the rays that enter it. The packet's reach is the largest
    /// `t_max` after it. Returns the rays still live; the walk stops when none are.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn packet_walk<const ORDER: u8, S>(
        &self,
        state: &mut S,
        t_max: &mut [f64],
        all: u64,
        packet_hit: impl Fn(&Node, f32) -> (u32, [f32; WIDTH]),
        ray_hit: impl Fn(&mut S, usize, &Node, f64) -> Option<(u32, [f32; WIDTH])>,
        mut per_ray: impl FnMut(
            &mut S,
            &Node,
            u32,
            u32,
            u64,
            &[f32; WIDTH],
            &mut [f64],
            &mut u64,
        ) -> Option<[u64; WIDTH]>,
        fetch_below: impl Fn(u32),
    ) -> u64 {
        let farthest = |t_max: &[f64]| t_max.iter().fold(f64::NEG_INFINITY, |a, &t| a.max(t));
        let mut far = farthest(t_max);
        let mut stack = [const { MaybeUninit::<(u32, f32, u64)>::uninit() }; STACK_DEPTH];
        let mut top = 0;
        let mut index = 0usize;
        let mut active = all;
        let mut live = all;
        loop {
            let node = &self.nodes[index];
            let many = active & (active - 1) != 0;
            let own = if many {
                None
            } else {
                let i = active.trailing_zeros() as usize;
                ray_hit(state, i, node, t_max[i])
            };
            let (mask, dist) = own.unwrap_or_else(|| packet_hit(node, t_max_f32(far)));
            let leaves = mask & leaf_mask(node);
            let mut inner = mask & !leaves;
            let parts = leaves != 0 || (inner & inner.wrapping_sub(1) != 0 && many);
            let split = if parts {
                let before = live;
                let split = per_ray(state, node, leaves, inner, active, &dist, t_max, &mut live);
                if live != before {
                    if live == 0 {
                        return 0;
                    }
                    let mut gone = before & !live;
                    while gone != 0 {
                        t_max[gone.trailing_zeros() as usize] = f64::NEG_INFINITY;
                        gone &= gone - 1;
                    }
                }
                far = farthest(t_max);
                split
            } else {
                None
            };
            if let Some(split) = split {
                // Children no ray enters by its own test are skipped.
                for (c, rays) in split.iter().enumerate() {
                    if *rays == 0 {
                        inner &= !(1 << c);
                    }
                }
            }
            let rays_of = |c: usize| split.map_or(active & live, |s| s[c]);
            if inner != 0 {
                let c = inner.trailing_zeros() as usize;
                inner &= inner - 1;
                let mut near = (node.index[c], dist[c], rays_of(c));
                prefetch(&self.nodes, near.0);
                fetch_below(near.0);
                if inner != 0 {
                    // Two or more interior children: push all but the first in `ORDER`, so
                    // that they pop in order.
                    let mut rest = [(0u32, 0f32, 0u64); WIDTH - 1];
                    let mut n = 0;
                    while inner != 0 {
                        let c = inner.trailing_zeros() as usize;
                        inner &= inner - 1;
                        let mut child = (node.index[c], dist[c], rays_of(c));
                        prefetch(&self.nodes, child.0);
                        fetch_below(child.0);
                        if farther::<ORDER>(near.1, child.1) {
                            std::mem::swap(&mut child, &mut near);
                        }
                        let mut i = n;
                        while i > 0 && farther::<ORDER>(child.1, rest[i - 1].1) {
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
                if near.2 != 0 && near.1 as f64 <= far {
                    index = near.0 as usize;
                    active = near.2;
                    continue;
                }
            }
            // Skip subtrees that hits found since they were pushed have put out of reach,
            // and those whose rays have all left the packet.
            loop {
                if top == 0 {
                    return live;
                }
                top -= 1;
                // SAFETY: slot `top` was written by the push that raised `top` above it.
                let (n, entry, rays) = unsafe { stack[top].assume_init() };
                let rays = rays & live;
                if rays != 0 && entry as f64 <= far {
                    index = n as usize;
                    active = rays;
                    break;
                }
            }
        }
    }
}

/// Hands each ray in `active` every leaf child in `leaves` of `node` whose packet entry bound
/// (`packet_dist`) lies within the ray's `t_max`, the leaves named to `fetch` first (see
/// [`Bvh::traverse_packet`]); a ray for which `leaf` returns true is cleared from `live`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn hand_packet_leaves(
    node: &Node,
    leaves: u32,
    active: u64,
    packet_dist: &[f32; WIDTH],
    t_max: &mut [f64],
    live: &mut u64,
    fetch: &impl Fn(Range<usize>, Fetch),
    leaf: &mut impl FnMut(usize, Range<usize>, &mut f64) -> bool,
) {
    let range = |c: usize| {
        let first = node.index[c] as usize;
        first..first + node.count[c] as usize
    };
    let mut l = leaves;
    while l != 0 {
        let c = l.trailing_zeros() as usize;
        l &= l - 1;
        fetch(range(c), Fetch::Leaf);
    }
    let mut a = active;
    while a != 0 {
        let i = a.trailing_zeros() as usize;
        a &= a - 1;
        let mut l = leaves;
        while l != 0 {
            let c = l.trailing_zeros() as usize;
            l &= l - 1;
            if packet_dist[c] as f64 <= t_max[i] && leaf(i, range(c), &mut t_max[i]) {
                *live &= !(1 << i);
                break;
            }
        }
    }
}

/// Each ray's f32 single-ray set-up, made for the whole packet when first needed.
struct Singles {
    rays: [MaybeUninit<RayF32>; PACKET],
    ready: bool,
    /// The tree's [`reach`].
    reach: [f64; 3],
}

impl Singles {
    /// The set-ups, of which the first `rays.len()` are written.
    #[inline(always)]
    fn all(&mut self, rays: &[Ray]) -> &[MaybeUninit<RayF32>; PACKET] {
        if !self.ready {
            for (s, ray) in self.rays.iter_mut().zip(rays) {
                s.write(
                    RayF32::new(ray, self.reach)
                        .expect("PacketBounds::new and spans_fit checked the range"),
                );
            }
            self.ready = true;
        }
        &self.rays
    }

    #[inline(always)]
    fn get(&mut self, rays: &[Ray], i: usize) -> &RayF32 {
        assert!(i < rays.len(), "ray {i} of a packet of {}", rays.len());
        // SAFETY: `all` writes the first `rays.len()` entries, and `i` is one of them.
        unsafe { self.all(rays)[i].assume_init_ref() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Random small boxes around `scale`, offset by `offset`.
    fn boxes(n: usize, scale: f64, offset: f64, seed: u64) -> Vec<Aabb> {
        let mut next = crate::test_rng::uniform(seed);
        (0..n)
            .map(|_| {
                let c = DVec3::new(next(), next(), next()) * 10.0 * scale + offset;
                let e = DVec3::new(next(), next(), next()) * 0.3 * scale;
                Aabb {
                    min: c - e,
                    max: c + e,
                }
            })
            .collect()
    }

    /// A full packet from (5, 5, −20): an 8×8 fan of directions (x, y) = `step` × (column,
    /// row) + `offset`, towards `z`.
    fn fan(step: f64, offset: f64, z: f64) -> Vec<Ray> {
        let eye = DVec3::new(5.0, 5.0, -20.0);
        (0..PACKET)
            .map(|k| {
                let d = DVec3::new(
                    (k % 8) as f64 * step + offset,
                    (k / 8) as f64 * step + offset,
                    z,
                );
                Ray::new(eye, d.normalize())
            })
            .collect()
    }

    /// Per ray, leaves by first slot.
    type Met = Vec<Vec<usize>>;

    /// The leaves (by first slot) each ray of `rays` truly meets (by the f64 slab test), and
    /// those it is handed single-ray and in a packet. Both f32 walks are conservative, each
    /// with its own margins, so each holds the first; neither need hold the other.
    fn leaves_met(bvh: &Bvh, rays: &[Ray], t_max: f64, spread: Spread) -> (Met, Met, Met) {
        let walk = |exact: bool| -> Met {
            rays.iter()
                .map(|r| {
                    let mut met = Vec::new();
                    let leaf = |range: Range<usize>, _: &mut f64| {
                        met.push(range.start);
                        false
                    };
                    if exact {
                        bvh.traverse_f64(r, &mut t_max.clone(), leaf);
                    } else {
                        bvh.traverse(r, &mut t_max.clone(), leaf);
                    }
                    met.sort();
                    met
                })
                .collect()
        };
        let (exact, single) = (walk(true), walk(false));
        let mut packet = vec![Vec::new(); rays.len()];
        let mut limits = vec![t_max; rays.len()];
        bvh.traverse_packet(
            rays,
            &mut limits,
            spread,
            |_, _| {},
            |i, range, _| packet[i].push(range.start),
        );
        for p in &mut packet {
            p.sort();
        }
        (exact, single, packet)
    }

    #[test]
    fn a_packet_meets_every_leaf_each_of_its_rays_meets_alone() {
        let mut next = crate::test_rng::uniform(777);
        for (scale, offset) in [(1e-4, 0.0), (1.0, -2.0), (1e4, 1e5), (0.01, 1e3)] {
            let prims = boxes(3000, scale, offset, 31);
            // With spans, a ray left alone takes its own test (the large-tree walk).
            let (plain, spanned) = (Bvh::build(&prims), Bvh::build(&prims).with_spans());
            let centre = DVec3::splat(5.0 * scale + offset);
            for (k, bvh) in (0..80).map(|k| (k / 2, [&plain, &spanned][k % 2])) {
                // A bundle from one eye point (coherent, like a pixel block), or from scattered
                // origins in random directions (incoherent), of 1 to 64 rays.
                let n = 1 + (k * 13) % PACKET;
                let eye = centre + DVec3::new(next() - 0.5, next() - 0.5, 2.0) * 20.0 * scale;
                let aim =
                    centre + DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5) * 8.0 * scale;
                let rays: Vec<Ray> = (0..n)
                    .map(|_| {
                        if k % 4 == 3 {
                            let o = centre + DVec3::new(next(), next(), next()) * 10.0 * scale;
                            let d = DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5);
                            Ray::new(o, d.normalize())
                        } else {
                            let jitter = DVec3::new(next(), next(), next()) * 0.5 * scale;
                            Ray::new(eye, (aim + jitter - eye).normalize())
                        }
                    })
                    .collect();
                for t_max in [f64::INFINITY, 12.0 * scale] {
                    for spread in [Spread::Wide, Spread::Pixel] {
                        let (exact, _, packet) = leaves_met(bvh, &rays, t_max, spread);
                        for (s, p) in exact.iter().zip(&packet) {
                            assert!(
                                s.iter().all(|leaf| p.binary_search(leaf).is_ok()),
                                "scale {scale}, packet {k}, {spread:?}: a leaf met alone was \
                                 skipped"
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn every_leaf_is_named_to_fetch_before_it_is_tested() {
        use std::cell::RefCell;
        let prims = boxes(3000, 1.0, 0.0, 21);
        let bvh = Bvh::build_aligned(&prims, 4).with_spans();
        // Off the axes: an axis-parallel ray would send the packet down the single-ray path,
        // which names nothing.
        let rays = fan(0.04, 0.01, 1.0);
        for spread in [Spread::Wide, Spread::Pixel] {
            let fetched = RefCell::new(Vec::new());
            let mut tested = 0;
            let mut limits = vec![f64::INFINITY; rays.len()];
            bvh.traverse_packet(
                &rays,
                &mut limits,
                spread,
                |range, what| {
                    if what == Fetch::Subtree {
                        assert!(range.len() <= SUBTREE_FETCH_SLOTS as usize);
                    }
                    fetched.borrow_mut().push((range, what));
                },
                |_, range, _| {
                    assert!(fetched.borrow().contains(&(range, Fetch::Leaf)));
                    tested += 1;
                },
            );
            let subtrees = fetched
                .borrow()
                .iter()
                .filter(|f| f.1 == Fetch::Subtree)
                .count();
            assert!(
                tested > 50 && subtrees > 10,
                "{spread:?}: {tested} leaves, {subtrees} subtrees"
            );
        }
    }

    #[test]
    fn packets_with_unsafe_or_mixed_rays_still_meet_every_leaf() {
        let prims = boxes(2000, 1.0, 0.0, 5);
        let bvh = Bvh::build(&prims);
        // Directions on both sides of every axis, and one axis-parallel ray (f64 fallback).
        let eye = DVec3::new(5.0, 5.0, -20.0);
        let mut rays: Vec<Ray> = (0..9)
            .map(|k| {
                let d = DVec3::new(k as f64 % 3.0 - 0.7, (k / 3) as f64 - 0.7, 3.0);
                Ray::new(eye, d.normalize())
            })
            .collect();
        let (exact, _, packet) = leaves_met(&bvh, &rays, f64::INFINITY, Spread::Wide);
        assert!(PacketBounds::new(&rays).is_some_and(|p| p.mixed == [true, true, false]));
        assert!(exact.iter().map(|s| s.len()).sum::<usize>() > 0);
        for (s, p) in exact.iter().zip(&packet) {
            assert!(s.iter().all(|leaf| p.binary_search(leaf).is_ok()));
        }
        rays.push(Ray::new(eye, DVec3::Z));
        assert!(PacketBounds::new(&rays).is_none());
        let (_, single, packet) = leaves_met(&bvh, &rays, f64::INFINITY, Spread::Wide);
        assert_eq!(single, packet);
        assert!(PacketBounds::new(&[]).is_none());
    }

    #[test]
    fn the_two_product_slab_bounds_are_the_four_product_ones() {
        let mut next = crate::test_rng::uniform(4242);
        let mut axes = 0;
        for k in 0..300 {
            let scale = [1e-3, 1.0, 1e3][k % 3];
            // Scattered origins, directions within a cone (so most axes are not mixed).
            let base = DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5);
            let rays: Vec<Ray> = (0..1 + k % PACKET)
                .map(|_| {
                    let o = DVec3::new(next(), next(), next()) * scale * (k % 2) as f64;
                    let d = base + DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5) * 0.2;
                    Ray::new(o, d.normalize())
                })
                .collect();
            let Some(p) = PacketBounds::new(&rays) else {
                continue;
            };
            for a in (0..3).filter(|&a| !p.mixed[a]) {
                axes += 1;
                for _ in 0..20 {
                    let (near, far) = ((next() - 0.5) as f32 * 4.0, (next() - 0.5) as f32 * 4.0);
                    let (near, far) = (near * scale as f32, far * scale as f32);
                    let (i0, i1) = (p.inv_lo[a], p.inv_hi[a]);
                    let (n0, n1) = (near - p.o_hi[a], near - p.o_lo[a]);
                    let (f0, f1) = (far - p.o_hi[a], far - p.o_lo[a]);
                    let tn = (n0 * i0).min(n0 * i1).min((n1 * i0).min(n1 * i1));
                    let tf = (f0 * i0).max(f0 * i1).max((f1 * i0).max(f1 * i1));
                    assert_eq!(p.slab(a, near, far), (tn, tf), "axis {a} of packet {k}");
                }
            }
        }
        assert!(axes > 300, "{axes} axes checked");
    }

    #[test]
    fn a_packet_that_misses_the_tree_meets_no_leaf() {
        let prims = boxes(500, 1.0, 0.0, 9);
        let bvh = Bvh::build(&prims);
        // Looking away from the boxes.
        let rays = fan(0.01, 0.003, -1.0);
        let mut limits = vec![f64::INFINITY; rays.len()];
        let mut met = 0;
        for spread in [Spread::Wide, Spread::Pixel] {
            bvh.traverse_packet(&rays, &mut limits, spread, |_, _| {}, |_, _, _| met += 1);
        }
        assert_eq!(met, 0);
        let packet = PacketBounds::new(&rays).unwrap();
        assert!(!packet.may_hit(&bvh.bounds(), f64::INFINITY));
        let behind = Ray::new(rays[0].origin, DVec3::new(0.01, 0.02, 1.0).normalize());
        assert!(PacketBounds::new(&[behind])
            .unwrap()
            .may_hit(&bvh.bounds(), f64::INFINITY));
    }

    #[test]
    fn a_closest_hit_packet_is_handed_a_nodes_leaves_nearest_first() {
        // Eight boxes in a row along x under one node, and packets of rays along the row one
        // way and the other: whichever way the builder ordered the slots, the leaves must come
        // nearest first for the packet (any-hit walks keep their own order).
        let prims: Vec<Aabb> = (0..8)
            .map(|i| {
                let c = DVec3::new(i as f64 * 3.0, 0.0, 0.0);
                Aabb {
                    min: c - DVec3::splat(1.0),
                    max: c + DVec3::splat(1.0),
                }
            })
            .collect();
        let bvh = Bvh::build(&prims);
        for (start, dir) in [(-10.0, 1.0), (40.0, -1.0)] {
            let rays: Vec<Ray> = (0..16)
                .map(|i| {
                    let o = DVec3::new(start, (i % 4) as f64 * 0.1, (i / 4) as f64 * 0.1);
                    Ray::new(o, DVec3::new(dir, 0.01, 0.02).normalize())
                })
                .collect();
            let packet = PacketBounds::new(&rays).unwrap();
            let mut t_max = vec![f64::INFINITY; rays.len()];
            // Per leaf handed, its boxes and how far along the rays its nearest one lies.
            let mut handed = Vec::new();
            bvh.traverse_packet_leaves(&packet, &mut t_max, |slots, _| {
                let leaf: Vec<usize> = slots.map(|slot| bvh.order[slot] as usize).collect();
                let near = leaf
                    .iter()
                    .map(|&p| dir * prims[p].min.x)
                    .fold(f64::MAX, f64::min);
                handed.push((near, leaf));
            });
            assert_eq!(handed.iter().map(|(_, l)| l.len()).sum::<usize>(), 8);
            assert!(handed.len() > 1, "one leaf: nothing to order");
            assert!(
                handed.windows(2).all(|w| w[0].0 < w[1].0),
                "{dir}: {handed:?}"
            );
        }
    }

    #[test]
    fn an_any_hit_packet_blocks_exactly_the_rays_blocked_alone() {
        let mut next = crate::test_rng::uniform(4242);
        let (mut blocked, mut open) = (0, 0);
        for (scale, offset) in [(1e-4, 0.0), (1.0, -2.0), (1e4, 1e5)] {
            let prims = boxes(1500, scale, offset, 77);
            let (plain, spanned) = (Bvh::build(&prims), Bvh::build(&prims).with_spans());
            let centre = DVec3::splat(5.0 * scale + offset);
            for (k, bvh) in (0..120).map(|k| (k / 2, [&plain, &spanned][k % 2])) {
                // Shadow-like rays from points in the boxes' region toward one light (some
                // blocked, some not), rays in scattered directions of mixed signs, and an
                // axis-parallel ray (f64 fallback) in some packets; 1 to 64 rays each.
                let n = 1 + (k * 11) % PACKET;
                let light = centre + DVec3::new(next() - 0.5, 3.0, next() - 0.5) * 10.0 * scale;
                let rays: Vec<(Ray, f64)> = (0..n)
                    .map(|i| {
                        let o = centre + DVec3::new(next(), next(), next()) * 10.0 * scale;
                        let to = match k % 3 {
                            0 => light - o,
                            _ => DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5),
                        };
                        let mut d = to.normalize();
                        if k % 5 == 4 && i == n / 2 {
                            d = DVec3::Y;
                        }
                        let t_max = match k % 4 {
                            0 => f64::INFINITY,
                            1 => 2.0 * scale,
                            _ => to.length(),
                        };
                        (Ray::new(o, d), t_max)
                    })
                    .collect();
                let hit = |ray: &Ray, range: Range<usize>, t_max: f64| {
                    range.into_iter().any(|s| {
                        let p = bvh.order[s] as usize;
                        p < prims.len() && prims[p].hit(ray, t_max).is_some()
                    })
                };
                let single: Vec<bool> = rays
                    .iter()
                    .map(|(r, t)| bvh.traverse_any(r, &mut t.clone(), |s, t| hit(r, s, *t)))
                    .collect();
                let only: Vec<Ray> = rays.iter().map(|r| r.0).collect();
                let mut limits: Vec<f64> = rays.iter().map(|r| r.1).collect();
                let mask = bvh.traverse_packet_any(
                    &only,
                    &mut limits,
                    |_, _| {},
                    |i, s, t| hit(&only[i], s, *t),
                );
                for (i, &alone) in single.iter().enumerate() {
                    assert_eq!(
                        mask & (1 << i) != 0,
                        alone,
                        "scale {scale}, packet {k}, ray {i}"
                    );
                    if alone {
                        assert_eq!(limits[i], f64::NEG_INFINITY);
                    }
                    blocked += alone as usize;
                    open += !alone as usize;
                }
                assert_eq!(mask & !(u64::MAX >> (64 - n)), 0);
            }
        }
        assert!(
            blocked > 300 && open > 300,
            "{blocked} blocked, {open} open"
        );
        assert_eq!(
            Bvh::build(&[]).traverse_packet_any(&[], &mut [], |_, _| {}, |_, _, _| true),
            0
        );
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_packet_test_matches_the_scalar_one() {
        if !std::arch::is_x86_feature_detected!("avx2") {
            return;
        }
        let bvh = Bvh::build(&boxes(3000, 1.0, 0.0, 11));
        let mut next = crate::test_rng::uniform(3);
        let mut hits = 0;
        for k in 0..300 {
            let eye = DVec3::new(next(), next(), next()) * 40.0 - 15.0;
            let aim = DVec3::new(next(), next(), next()) * 10.0;
            let rays: Vec<Ray> = (0..16)
                .map(|_| {
                    let spread = if k % 3 == 0 { 10.0 } else { 0.5 };
                    let d = aim + DVec3::new(next(), next(), next()) * spread - eye;
                    Ray::new(eye, d.normalize())
                })
                .collect();
            let p = PacketBounds::new(&rays).unwrap();
            let t_max = if k % 2 == 0 { f32::INFINITY } else { 25.0 };
            for node in &bvh.nodes {
                let scalar = p.hit(node, t_max);
                // SAFETY: AVX2 was detected above.
                let avx = unsafe { p.hit_avx2(node, t_max) };
                assert_eq!(scalar.0, avx.0);
                for c in 0..WIDTH {
                    if scalar.0 & (1 << c) != 0 {
                        assert_eq!(scalar.1[c].to_bits(), avx.1[c].to_bits());
                    }
                }
                hits += scalar.0.count_ones();
            }
        }
        assert!(hits > 1000, "{hits} box hits");
    }
}
