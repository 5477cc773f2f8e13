use glam::DVec3;

use crate::geometry::{Aabb, Ray};

/// A flattened BVH node, one cache line. The first child of an interior node follows it
/// directly; `offset` holds the second child. A leaf covers primitives
/// `offset..offset + count` of the owner's reordered primitive array.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub struct Node {
    pub bounds: Aabb,
    pub offset: u32,
    /// 0 for interior nodes.
    pub count: u32,
    /// Split axis of an interior node: traversal visits the child nearer the ray first.
    pub axis: u8,
}

/// A BVH over primitives known only by their bounds; the owner intersects them through a
/// closure, so this module knows no geometry.
#[derive(Clone, Debug, Default)]
pub struct Bvh {
    pub nodes: Vec<Node>,
    /// `order[i]` is the original index of the primitive the owner must store at slot i.
    pub order: Vec<u32>,
}

const BINS: usize = 16;
const MAX_LEAF: usize = 4;
const TRAVERSAL_COST: f64 = 1.0;
const INTERSECT_COST: f64 = 1.0;
const STACK_DEPTH: usize = 96;

struct Builder<'a> {
    bounds: &'a [Aabb],
    centroids: Vec<DVec3>,
    nodes: Vec<Node>,
}

impl Bvh {
    /// Builds with the binned surface-area heuristic (16 bins on each axis).
    pub fn build(bounds: &[Aabb]) -> Bvh {
        let mut order: Vec<u32> = (0..bounds.len() as u32).collect();
        if bounds.is_empty() {
            return Bvh {
                nodes: Vec::new(),
                order,
            };
        }
        let mut builder = Builder {
            bounds,
            centroids: bounds.iter().map(Aabb::centroid).collect(),
            nodes: Vec::with_capacity(2 * bounds.len() / MAX_LEAF + 1),
        };
        builder.build_node(&mut order, 0, 0);
        Bvh {
            nodes: builder.nodes,
            order,
        }
    }

    pub fn bounds(&self) -> Aabb {
        self.nodes.first().map_or(Aabb::EMPTY, |n| n.bounds)
    }

    pub fn depth(&self) -> usize {
        fn depth(nodes: &[Node], i: usize) -> usize {
            let n = &nodes[i];
            if n.count > 0 {
                1
            } else {
                1 + depth(nodes, i + 1).max(depth(nodes, n.offset as usize))
            }
        }
        if self.nodes.is_empty() {
            0
        } else {
            depth(&self.nodes, 0)
        }
    }

    /// Visits every leaf the ray may reach before `*t_max`, nearest subtree first. `leaf`
    /// gets a primitive range and shrinks `t_max` when it finds a closer hit; returning true
    /// stops the traversal (any-hit queries).
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
        let negative = [ray.dir.x < 0.0, ray.dir.y < 0.0, ray.dir.z < 0.0];
        let mut stack = [0u32; STACK_DEPTH];
        let mut top = 0;
        let mut index = 0usize;
        loop {
            let node = &self.nodes[index];
            if node.bounds.hit(ray, *t_max).is_some() {
                if node.count > 0 {
                    let start = node.offset as usize;
                    if leaf(start..start + node.count as usize, t_max) {
                        return true;
                    }
                } else {
                    let (near, far) = if negative[node.axis as usize] {
                        (node.offset as usize, index + 1)
                    } else {
                        (index + 1, node.offset as usize)
                    };
                    stack[top] = far as u32;
                    top += 1;
                    index = near;
                    continue;
                }
            }
            if top == 0 {
                return false;
            }
            top -= 1;
            index = stack[top] as usize;
        }
    }
}

impl Builder<'_> {
    fn build_node(&mut self, prims: &mut [u32], first: usize, depth: usize) -> usize {
        let node_index = self.nodes.len();
        let bounds = prims
            .iter()
            .fold(Aabb::EMPTY, |b, &p| b.union(self.bounds[p as usize]));
        self.nodes.push(Node {
            bounds: bounds.padded(),
            offset: first as u32,
            count: prims.len() as u32,
            axis: 0,
        });
        // The depth cap keeps traversal's fixed stack from overflowing on adversarial input.
        if prims.len() <= 1 || depth + 2 >= STACK_DEPTH {
            return node_index;
        }
        let Some(split) = self.find_split(prims, bounds) else {
            return node_index;
        };
        let axis = split.axis;
        let mid = partition(prims, |&p| {
            split.goes_left(self.centroids[p as usize][axis])
        });
        if mid == 0 || mid == prims.len() {
            return node_index;
        }
        let (left, right) = prims.split_at_mut(mid);
        self.build_node(left, first, depth + 1);
        let right_index = self.build_node(right, first + mid, depth + 1);
        let node = &mut self.nodes[node_index];
        node.offset = right_index as u32;
        node.count = 0;
        node.axis = axis as u8;
        node_index
    }

    /// The cheapest binned SAH split, or None when a leaf is cheaper and small enough.
    fn find_split(&self, prims: &[u32], bounds: Aabb) -> Option<Split> {
        let centroid_bounds = prims
            .iter()
            .fold(Aabb::EMPTY, |b, &p| b.grow(self.centroids[p as usize]));
        let extent = centroid_bounds.extent();
        let mut best: Option<(f64, usize, usize)> = None;
        for axis in 0..3 {
            if !(extent[axis] > 0.0) {
                continue;
            }
            let lo = centroid_bounds.min[axis];
            let scale = BINS as f64 / extent[axis];
            let mut bin_bounds = [Aabb::EMPTY; BINS];
            let mut bin_counts = [0usize; BINS];
            for &p in prims {
                let b = bin_of(self.centroids[p as usize][axis], lo, scale);
                bin_counts[b] += 1;
                bin_bounds[b] = bin_bounds[b].union(self.bounds[p as usize]);
            }
            // Sweep from the right to get each suffix's area and count, then from the left.
            let mut right_area = [0.0; BINS];
            let mut right_count = [0usize; BINS];
            let mut acc = Aabb::EMPTY;
            let mut count = 0;
            for i in (1..BINS).rev() {
                acc = acc.union(bin_bounds[i]);
                count += bin_counts[i];
                right_area[i] = acc.surface_area();
                right_count[i] = count;
            }
            let mut acc = Aabb::EMPTY;
            let mut count = 0;
            for split in 1..BINS {
                acc = acc.union(bin_bounds[split - 1]);
                count += bin_counts[split - 1];
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
        let (cost, axis, split) = best?;
        let area = bounds.surface_area();
        let split_cost = TRAVERSAL_COST + INTERSECT_COST * cost / area.max(f64::MIN_POSITIVE);
        let leaf_cost = INTERSECT_COST * prims.len() as f64;
        if prims.len() <= MAX_LEAF && leaf_cost <= split_cost {
            return None;
        }
        Some(Split {
            axis,
            lo: centroid_bounds.min[axis],
            scale: BINS as f64 / extent[axis],
            bin: split,
        })
    }
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

    #[test]
    fn every_primitive_sits_in_exactly_one_leaf_inside_its_bounds() {
        let prims = boxes(5000);
        let bvh = Bvh::build(&prims);
        let mut seen = vec![0; prims.len()];
        for node in bvh.nodes.iter().filter(|n| n.count > 0) {
            for slot in node.offset..node.offset + node.count {
                let p = bvh.order[slot as usize] as usize;
                seen[p] += 1;
                let b = prims[p];
                assert!(node.bounds.min.cmple(b.min).all() && node.bounds.max.cmpge(b.max).all());
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
    fn identical_centroids_make_one_leaf() {
        let b = Aabb {
            min: DVec3::ZERO,
            max: DVec3::ONE,
        };
        let bvh = Bvh::build(&vec![b; 100]);
        assert_eq!(bvh.nodes.len(), 1);
        assert_eq!(bvh.nodes[0].count, 100);
    }
}
