//! The broad phase: a bounding volume hierarchy of axis-aligned boxes, built top-down by
//! median splits along the longest axis, rebuilt at each configuration (a few milliseconds
//! for ten thousand boxes, less than one assembly of the mesh they bound).

use nalgebra::Vector3;

/// An axis-aligned box.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Aabb {
    pub(crate) min: Vector3<f64>,
    pub(crate) max: Vector3<f64>,
}

impl Aabb {
    pub(crate) fn empty() -> Self {
        Self {
            min: Vector3::repeat(f64::INFINITY),
            max: Vector3::repeat(f64::NEG_INFINITY),
        }
    }

    /// The box of `points`.
    pub(crate) fn of(points: impl IntoIterator<Item = Vector3<f64>>) -> Self {
        let mut b = Self::empty();
        for p in points {
            b.min = b.min.inf(&p);
            b.max = b.max.sup(&p);
        }
        b
    }

    fn merge(&self, o: &Aabb) -> Aabb {
        Aabb {
            min: self.min.inf(&o.min),
            max: self.max.sup(&o.max),
        }
    }

    /// The box grown by `r` on every side.
    pub(crate) fn inflate(&self, r: f64) -> Aabb {
        Aabb {
            min: self.min.add_scalar(-r),
            max: self.max.add_scalar(r),
        }
    }

    pub(crate) fn overlaps(&self, o: &Aabb) -> bool {
        (0..3).all(|k| self.min[k] <= o.max[k] && o.min[k] <= self.max[k])
    }

    fn center(&self) -> Vector3<f64> {
        (self.min + self.max) * 0.5
    }
}

/// A node: a box and either two children or a range of `order`.
#[derive(Debug, Clone)]
struct Node {
    aabb: Aabb,
    /// Leaf: `order[start..end]`; inner node: children `start` and `end` (node indices).
    start: usize,
    end: usize,
    leaf: bool,
}

/// A hierarchy over a list of boxes.
#[derive(Debug, Clone)]
pub(crate) struct Bvh {
    nodes: Vec<Node>,
    order: Vec<usize>,
    boxes: Vec<Aabb>,
}

/// Boxes per leaf.
const LEAF: usize = 4;

impl Bvh {
    pub(crate) fn new(boxes: Vec<Aabb>) -> Self {
        let mut bvh = Self {
            nodes: Vec::with_capacity(2 * boxes.len() / LEAF + 1),
            order: (0..boxes.len()).collect(),
            boxes,
        };
        if !bvh.boxes.is_empty() {
            bvh.build(0, bvh.order.len());
        }
        bvh
    }

    /// Builds the node over `order[start..end]` and returns its index.
    fn build(&mut self, start: usize, end: usize) -> usize {
        let aabb = self.order[start..end]
            .iter()
            .fold(Aabb::empty(), |b, &i| b.merge(&self.boxes[i]));
        let index = self.nodes.len();
        self.nodes.push(Node {
            aabb,
            start,
            end,
            leaf: true,
        });
        if end - start <= LEAF {
            return index;
        }
        let centers = Aabb::of(
            self.order[start..end]
                .iter()
                .map(|&i| self.boxes[i].center()),
        );
        let axis = (centers.max - centers.min).imax();
        let mid = (start + end) / 2;
        let boxes = &self.boxes;
        self.order[start..end].select_nth_unstable_by(mid - start, |&a, &b| {
            boxes[a].center()[axis].total_cmp(&boxes[b].center()[axis])
        });
        let left = self.build(start, mid);
        let right = self.build(mid, end);
        let node = &mut self.nodes[index];
        (node.start, node.end, node.leaf) = (left, right, false);
        index
    }

    /// Calls `found` with each box (by index, in a fixed order) that overlaps `probe`.
    pub(crate) fn query(&self, probe: &Aabb, mut found: impl FnMut(usize)) {
        if self.nodes.is_empty() {
            return;
        }
        let mut stack = vec![0usize];
        while let Some(n) = stack.pop() {
            let node = &self.nodes[n];
            if !node.aabb.overlaps(probe) {
                continue;
            }
            if node.leaf {
                for &i in &self.order[node.start..node.end] {
                    if self.boxes[i].overlaps(probe) {
                        found(i);
                    }
                }
            } else {
                stack.push(node.end);
                stack.push(node.start);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The hierarchy finds exactly the boxes that a brute-force scan finds.
    #[test]
    fn finds_what_brute_force_finds() {
        let mut seed = 7u64;
        let mut next = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        let boxes: Vec<Aabb> = (0..500)
            .map(|_| {
                let p = Vector3::new(next(), next(), next());
                Aabb::of([p, p + Vector3::new(next(), next(), next()) * 0.05])
            })
            .collect();
        let bvh = Bvh::new(boxes.clone());
        for probe in boxes.iter().step_by(7) {
            let probe = probe.inflate(0.02);
            let mut found = Vec::new();
            bvh.query(&probe, |i| found.push(i));
            found.sort_unstable();
            let expected: Vec<usize> = (0..boxes.len())
                .filter(|&i| boxes[i].overlaps(&probe))
                .collect();
            assert_eq!(found, expected);
        }
    }
}
