//! The top level's own traversal over the nodes of the objects' BVH.
//!
//! The accel module's generic traversal serves meshes of any size; the top level of a course
//! scene holds a few dozen objects, and there the per-ray and per-node overheads decided the
//! cost (a third of a stacks.scene render was traversal bookkeeping: working out which
//! children are leaves, bounds checks, the branchy f32 ray set-up). This copy of the nodes
//! keeps each node's leaf mask and walks them with the generic traversal's own ray set-up and
//! box test ([`RayF32`]), so exactly the boxes the generic test enters are entered (it is
//! conservative: a box the f64 test would enter is never culled), and leaves are handed to the
//! caller slot by slot.

use std::mem::MaybeUninit;

use crate::accel::{t_limit, Bounds, Bvh, Node, RayF32};
use crate::geometry::Ray;

/// Children per top-level node.
const WIDTH: usize = 8;
/// Marks a stack entry of [`TopLevel::walk_nearest`] as a leaf (node index and child slot).
const LEAF: u32 = 1 << 31;
/// Deepest binary tree the builder makes (accel's `MAX_DEPTH`); a wide node is never deeper,
/// and each level pushes at most `WIDTH - 1` siblings.
const MAX_DEPTH: usize = 96;
const STACK_DEPTH: usize = (WIDTH - 1) * MAX_DEPTH;

#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
struct TopNode {
    /// `bounds[2 * axis]`: the children's minima on `axis`; `bounds[2 * axis + 1]` maxima.
    /// Unused slots hold an empty box (min +∞, max −∞).
    bounds: Bounds,
    /// Per child: the child node's index, or a leaf's first slot.
    index: [u32; WIDTH],
    /// Per child: a leaf's slot count (0 for an interior child or an unused slot).
    count: [u32; WIDTH],
    /// The children that are leaves, one bit each.
    leaves: u32,
}

/// The top-level BVH's nodes in the traversal's own layout.
#[derive(Clone, Debug, Default)]
pub(super) struct TopLevel {
    nodes: Vec<TopNode>,
    /// Per axis, a bound on the magnitude of every box coordinate (see [`SLAB_MARGIN`]).
    reach: [f64; 3],
}

impl TopLevel {
    pub(super) fn new(bvh: &Bvh) -> TopLevel {
        assert!(
            bvh.depth() <= MAX_DEPTH,
            "BVH deeper than the builder's limit"
        );
        assert!(
            bvh.nodes.len() < (LEAF >> 3) as usize,
            "too many top-level nodes for walk_nearest's entries"
        );
        let nodes = bvh.nodes.iter().map(TopNode::from_node).collect();
        TopLevel {
            nodes,
            reach: bvh.reach(),
        }
    }

    /// Hands `leaf` the slots of every leaf the ray may reach before `*t_max` (which `leaf`
    /// shrinks as it finds closer hits): nearest child first, or farthest first with `ANY`,
    /// as the generic traversal orders them. Returns true as soon as `leaf` does. None when
    /// the ray is out of the f32 test's range (the caller then takes the generic traversal).
    #[inline(always)]
    pub(super) fn walk<const ANY: bool>(
        &self,
        ray: &Ray,
        t_max: &mut f64,
        mut leaf: impl FnMut(std::ops::Range<usize>, &mut f64) -> bool,
    ) -> Option<bool> {
        if self.nodes.is_empty() {
            return Some(false);
        }
        let r = RayF32::new(ray, self.reach)?;
        // Left uninitialised: only slots below `top`, each written first, are read.
        let mut stack = [const { MaybeUninit::<(u32, f32)>::uninit() }; STACK_DEPTH];
        let mut top = 0;
        let mut index = 0usize;
        // Entry distances are compared with `t_max`'s f32 bound, made again when a leaf
        // shrinks it (as the mesh walk does, `Bvh::traverse_with`).
        let mut limit = t_limit(*t_max);
        loop {
            let node = &self.nodes[index];
            let (mask, dist) = r.hit_top(node, limit);
            let mut leaves = mask & node.leaves;
            let mut inner = mask & !leaves;
            while leaves != 0 {
                let c = leaves.trailing_zeros() as usize % WIDTH;
                leaves &= leaves - 1;
                if dist[c] <= limit {
                    let first = node.index[c] as usize;
                    if leaf(first..first + node.count[c] as usize, t_max) {
                        return Some(true);
                    }
                    limit = t_limit(*t_max);
                }
            }
            if inner != 0 {
                let c = inner.trailing_zeros() as usize % WIDTH;
                inner &= inner - 1;
                let mut next = (node.index[c], dist[c]);
                if inner != 0 {
                    // Two or more interior children: visit the first in order now and push
                    // the rest so that they pop in order.
                    let mut rest = [(0u32, 0f32); WIDTH - 1];
                    let mut n = 0;
                    while inner != 0 {
                        let c = inner.trailing_zeros() as usize % WIDTH;
                        inner &= inner - 1;
                        let mut child = (node.index[c], dist[c]);
                        if later::<ANY>(next.1, child.1) {
                            std::mem::swap(&mut child, &mut next);
                        }
                        let mut i = n;
                        while i > 0 && later::<ANY>(child.1, rest[i - 1].1) {
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
                if next.1 <= limit {
                    index = next.0 as usize;
                    continue;
                }
            }
            // Skip subtrees that a hit found since they were pushed has put out of reach.
            match pop_within(&stack, &mut top, limit) {
                Some(n) => index = n as usize,
                None => return Some(false),
            }
        }
    }
}

/// Pops the stack's entries (node or leaf key, entry distance) below `*top` until one lies
/// within `limit` (a `t_max`'s [`t_limit`]), and returns its key; None when the stack runs
/// out.
#[inline(always)]
fn pop_within(stack: &[MaybeUninit<(u32, f32)>], top: &mut usize, limit: f32) -> Option<u32> {
    while *top > 0 {
        *top -= 1;
        // SAFETY: the walks write every slot below `top` before raising `top` above it.
        let (key, entry) = unsafe { stack[*top].assume_init() };
        if entry <= limit {
            return Some(key);
        }
    }
    None
}

impl TopLevel {
    /// [`TopLevel::walk`] for closest hits over leaves that cost far more than a node
    /// visit (mesh instances): leaves and interior children alike are taken nearest first
    /// by entry distance, a leaf only once every nearer box has been dealt with, so that a
    /// hit in a near instance culls the farther ones before they are entered. (`walk` tests
    /// a node's leaves at once, in slot order, before its nearer interior children: cheaper
    /// where a leaf is a sphere or a triangle.) The same leaves as `walk`'s may be handed,
    /// fewer where a hit culls them; the caller's ties make the hit the same either way.
    pub(super) fn walk_nearest(
        &self,
        ray: &Ray,
        t_max: &mut f64,
        mut leaf: impl FnMut(std::ops::Range<usize>, &mut f64) -> bool,
    ) -> Option<bool> {
        if self.nodes.is_empty() {
            return Some(false);
        }
        let r = RayF32::new(ray, self.reach)?;
        // Entries: an interior child's node index, or LEAF | node << 3 | child for a leaf.
        // Left uninitialised: only slots below `top`, each written first, are read.
        let mut stack = [const { MaybeUninit::<(u32, f32)>::uninit() }; STACK_DEPTH + WIDTH];
        let mut top = 0;
        let mut entry = 0u32;
        loop {
            if entry & LEAF != 0 {
                let node = &self.nodes[((entry & !LEAF) >> 3) as usize];
                let c = (entry & 7) as usize;
                let first = node.index[c] as usize;
                if leaf(first..first + node.count[c] as usize, t_max) {
                    return Some(true);
                }
            } else {
                let node = &self.nodes[entry as usize];
                let (mut mask, dist) = r.hit_top(node, t_limit(*t_max));
                // The node's children, farthest first, onto the stack (insertion into the
                // few slots above `top`).
                let base = top;
                while mask != 0 {
                    let c = mask.trailing_zeros() as usize % WIDTH;
                    mask &= mask - 1;
                    let key = if node.leaves & (1 << c) != 0 {
                        LEAF | (entry << 3) | c as u32
                    } else {
                        node.index[c]
                    };
                    let mut i = top;
                    // SAFETY: slots base..top were written by this loop.
                    while i > base && unsafe { stack[i - 1].assume_init() }.1 < dist[c] {
                        stack[i] = stack[i - 1];
                        i -= 1;
                    }
                    stack[i].write((key, dist[c]));
                    top += 1;
                }
            }
            // The nearest entry still within reach.
            match pop_within(&stack, &mut top, t_limit(*t_max)) {
                Some(key) => entry = key,
                None => return Some(false),
            }
        }
    }

    /// Hands `leaf` the slots of every leaf whose box is not wholly outside one of the planes
    /// through `origin` with inward normals `planes` (a pixel's bundle of eye rays): a
    /// superset of the leaves any of those rays can reach.
    pub(super) fn frustum(
        &self,
        origin: glam::DVec3,
        planes: &[glam::DVec3; 4],
        leaf: &mut impl FnMut(std::ops::Range<usize>),
    ) {
        if !self.nodes.is_empty() {
            self.frustum_from(0, origin, planes, leaf);
        }
    }

    fn frustum_from(
        &self,
        index: usize,
        origin: glam::DVec3,
        planes: &[glam::DVec3; 4],
        leaf: &mut impl FnMut(std::ops::Range<usize>),
    ) {
        let node = &self.nodes[index];
        for c in 0..WIDTH {
            if node.index[c] == u32::MAX {
                continue;
            }
            if super::box_behind_a_plane(&node.bounds, c, origin, planes) {
                continue;
            }
            let first = node.index[c] as usize;
            if node.count[c] > 0 {
                leaf(first..first + node.count[c] as usize);
            } else {
                self.frustum_from(first, origin, planes, leaf);
            }
        }
    }
}

/// Whether a child at entry distance `a` is visited after one at `b`: nearest first for
/// closest hits, farthest first for any-hit queries (a shadow ray's blockers tend to lie
/// away from the surface it leaves).
#[inline(always)]
fn later<const ANY: bool>(a: f32, b: f32) -> bool {
    if ANY {
        a < b
    } else {
        a > b
    }
}

impl TopNode {
    fn from_node(node: &Node) -> TopNode {
        let width = node.index.len();
        assert!(width <= WIDTH, "accel nodes wider than the top level's");
        let mut out = TopNode {
            bounds: [
                [f32::INFINITY; WIDTH],
                [f32::NEG_INFINITY; WIDTH],
                [f32::INFINITY; WIDTH],
                [f32::NEG_INFINITY; WIDTH],
                [f32::INFINITY; WIDTH],
                [f32::NEG_INFINITY; WIDTH],
            ],
            index: [u32::MAX; WIDTH],
            count: [0; WIDTH],
            leaves: 0,
        };
        for c in 0..width {
            for row in 0..6 {
                out.bounds[row][c] = node.bounds[row][c];
            }
            out.index[c] = node.index[c];
            out.count[c] = node.count[c].into();
        }
        out.leaves = node.leaves.into();
        out
    }
}

/// The top level's node test, on the mesh walk's per-ray constants.
impl RayF32 {
    /// Hit mask and conservative entry distances of a node's boxes: the mesh walk's own box
    /// test ([`RayF32`]), eight lanes at once where the build has AVX2 (the binaries' default
    /// target, x86-64-v3), else the four-lane SSE or scalar form, so exactly the boxes the
    /// generic traversal enters are entered.
    #[inline(always)]
    fn hit_top(&self, node: &TopNode, t_far: f32) -> (u32, [f32; WIDTH]) {
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
        // SAFETY: AVX2 is enabled for the whole build (cfg above).
        return unsafe { self.hit_avx2_below(&node.bounds, t_far) };
        #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
        return self.hit_below(&node.bounds, t_far);
    }
}

#[cfg(test)]
mod tests {
    use glam::DVec3;

    use super::*;
    use crate::geometry::Aabb;

    /// Every box a ray meets in f64 is handed out, at scales from 1e-4 to 1e5.
    #[test]
    fn the_walk_never_skips_a_box_the_ray_meets() {
        let mut next = crate::test_rng::uniform(77);
        for (scale, offset) in [(1e-4, 0.0), (1e-4, 3.7), (1.0, -2.0), (1e5, 1e5)] {
            let prims: Vec<Aabb> = (0..300)
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
            let top = TopLevel::new(&bvh);
            for i in 0..400 {
                // Aim at a corner, an edge or a face of some box as often as inside it: the
                // grazing rays are the ones an f32 rounding could turn away.
                let target = prims[i % prims.len()];
                let pick = |k: f64, a: f64, b: f64| match (k * 3.0) as u32 {
                    0 => a,
                    1 => b,
                    _ => a + (b - a) * k,
                };
                let aim = DVec3::new(
                    pick(next(), target.min.x, target.max.x),
                    pick(next(), target.min.y, target.max.y),
                    pick(next(), target.min.z, target.max.z),
                );
                let dir = DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5).normalize();
                let origin = aim - dir * scale * 10f64.powf(next() * 4.0 - 1.0);
                let ray = Ray::new(origin, dir);
                let t_max = if i % 2 == 0 {
                    f64::INFINITY
                } else {
                    scale * 5.0
                };
                for any in [false, true] {
                    let mut found = vec![false; prims.len()];
                    let mut limit = t_max;
                    let mark = |slots: std::ops::Range<usize>, _: &mut f64| {
                        for slot in slots {
                            found[bvh.order[slot] as usize] = true;
                        }
                        false
                    };
                    let walked = match (any, i % 3) {
                        (true, _) => top.walk::<true>(&ray, &mut limit, mark),
                        (false, 0) => top.walk_nearest(&ray, &mut limit, mark),
                        (false, _) => top.walk::<false>(&ray, &mut limit, mark),
                    };
                    assert_eq!(walked, Some(false));
                    for (p, b) in prims.iter().enumerate() {
                        if b.hit(&ray, t_max).is_some() {
                            assert!(found[p], "scale {scale}: box {p} skipped for ray {i}");
                        }
                    }
                }
            }
        }
    }

    /// The nearest-first walk hands leaves in order of their boxes' entry distance, each
    /// once, and with a leaf test that finds "hits" at box entry (shrinking t_max), ends with
    /// the nearest box a brute force finds, having handed fewer boxes than the slot-order walk
    /// (543 against 591 here).
    #[test]
    fn the_nearest_first_walk_hands_leaves_in_order_and_culls_behind_hits() {
        let mut next = crate::test_rng::uniform(5);
        let prims: Vec<Aabb> = (0..2000)
            .map(|_| {
                let c = DVec3::new(next(), next(), next()) * 40.0;
                let e = DVec3::new(next(), next(), next()) * 1.5;
                Aabb {
                    min: c - e,
                    max: c + e,
                }
            })
            .collect();
        let bvh = Bvh::build(&prims);
        let top = TopLevel::new(&bvh);
        let (mut entered_nearest, mut entered_walk) = (0, 0);
        for _ in 0..500 {
            // From outside the crowd of boxes toward a point in it, as eye rays meet a crowd
            // of instances.
            let aim = DVec3::new(next(), next(), next()) * 40.0;
            let away = DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5).normalize();
            let origin = DVec3::splat(20.0) + away * 80.0;
            let ray = Ray::new(origin, (aim - origin).normalize());
            let nearest = (prims.iter())
                .filter_map(|b| b.hit(&ray, f64::INFINITY))
                .fold(f64::INFINITY, f64::min);
            for ordered in [true, false] {
                let mut handed = Vec::new();
                let mut limit = f64::INFINITY;
                let mut test = |slots: std::ops::Range<usize>, t_max: &mut f64| {
                    for slot in slots {
                        let b = prims[bvh.order[slot] as usize];
                        handed.push(slot);
                        if let Some(t0) = b.hit(&ray, *t_max) {
                            *t_max = t_max.min(t0);
                        }
                    }
                    false
                };
                let walked = if ordered {
                    top.walk_nearest(&ray, &mut limit, &mut test)
                } else {
                    top.walk::<false>(&ray, &mut limit, &mut test)
                };
                assert_eq!(walked, Some(false));
                assert_eq!(limit, nearest, "{ray:?}");
                let mut unique = handed.clone();
                unique.sort();
                unique.dedup();
                assert_eq!(unique.len(), handed.len(), "a leaf handed twice");
                if ordered {
                    entered_nearest += handed.len();
                } else {
                    entered_walk += handed.len();
                }
            }
        }
        assert!(
            entered_nearest < entered_walk,
            "nearest first entered {entered_nearest} boxes, slot order {entered_walk}"
        );
    }
}
