//! Broad phase for tool and cutting queries: a hashed uniform grid of points.
//!
//! Each point sits in one cell, in an intrusive doubly linked list per hash bucket, so
//! moving a point to another cell is O(1) and nothing is allocated after construction
//! (except when points are added by a cut). A query visits the cells that overlap a
//! box, so its cost follows the number of points near the tool, not the mesh size.
//! We use this instead of parry's BVH because the tissue moves every step: a BVH
//! would be refitted over all nodes each step, while here only the points that
//! change cell do any work.

use crate::math::Vec3;

const NONE: u32 = u32::MAX;

/// ⌊v⌋ as i32 without a libm call (f64::floor is one on baseline x86-64, and this runs
/// for every node every substep). `as` saturates and maps NaN to 0: a broken position
/// lands in some cell and is dealt with by the model's blow-up containment.
#[inline]
fn floor_i32(v: f64) -> i32 {
    let t = v as i32;
    t.saturating_sub(i32::from((t as f64) > v))
}

#[derive(Debug, Clone)]
pub struct PointGrid {
    inv_cell: f64,
    mask: usize,
    heads: Vec<u32>,
    next: Vec<u32>,
    prev: Vec<u32>,
    cell: Vec<[i32; 3]>,
    present: Vec<bool>,
    len: usize,
}

impl PointGrid {
    /// A grid with cells of `cell_m` metres for up to `capacity` point ids (grows on demand).
    pub fn new(cell_m: f64, capacity: usize) -> Self {
        assert!(cell_m > 0.0 && cell_m.is_finite(), "grid cell size must be positive");
        let buckets = (capacity * 2).max(1024).next_power_of_two();
        Self {
            inv_cell: 1.0 / cell_m,
            mask: buckets - 1,
            heads: vec![NONE; buckets],
            next: vec![NONE; capacity],
            prev: vec![NONE; capacity],
            cell: vec![[0; 3]; capacity],
            present: vec![false; capacity],
            len: 0,
        }
    }

    pub fn cell_size_m(&self) -> f64 {
        1.0 / self.inv_cell
    }

    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    fn cell_of(&self, p: &Vec3) -> [i32; 3] {
        [floor_i32(p.x * self.inv_cell), floor_i32(p.y * self.inv_cell), floor_i32(p.z * self.inv_cell)]
    }

    fn bucket(&self, c: [i32; 3]) -> usize {
        let h = (c[0] as u32 as u64).wrapping_mul(0x9e37_79b1)
            ^ (c[1] as u32 as u64).wrapping_mul(0x85eb_ca77)
            ^ (c[2] as u32 as u64).wrapping_mul(0xc2b2_ae3d);
        ((h ^ (h >> 29)) as usize) & self.mask
    }

    /// Makes room for ids below `capacity`.
    pub fn reserve_ids(&mut self, capacity: usize) {
        if capacity > self.next.len() {
            self.next.resize(capacity, NONE);
            self.prev.resize(capacity, NONE);
            self.cell.resize(capacity, [0; 3]);
            self.present.resize(capacity, false);
        }
    }

    pub fn insert(&mut self, id: u32, p: &Vec3) {
        self.reserve_ids(id as usize + 1);
        if self.present[id as usize] {
            self.update(id, p);
            return;
        }
        let c = self.cell_of(p);
        self.link(id, c);
        self.present[id as usize] = true;
        self.len += 1;
    }

    pub fn remove(&mut self, id: u32) {
        if self.present.get(id as usize).copied().unwrap_or(false) {
            self.unlink(id);
            self.present[id as usize] = false;
            self.len -= 1;
        }
    }

    /// Moves a point; O(1), and free when it stays in its cell.
    #[inline]
    pub fn update(&mut self, id: u32, p: &Vec3) {
        let c = self.cell_of(p);
        let i = id as usize;
        if self.cell[i] != c && self.present[i] {
            self.unlink(id);
            self.link(id, c);
        }
    }

    fn link(&mut self, id: u32, c: [i32; 3]) {
        let b = self.bucket(c);
        let i = id as usize;
        self.cell[i] = c;
        self.prev[i] = NONE;
        self.next[i] = self.heads[b];
        if self.heads[b] != NONE {
            self.prev[self.heads[b] as usize] = id;
        }
        self.heads[b] = id;
    }

    fn unlink(&mut self, id: u32) {
        let i = id as usize;
        let (p, n) = (self.prev[i], self.next[i]);
        if p != NONE {
            self.next[p as usize] = n;
        } else {
            let b = self.bucket(self.cell[i]);
            self.heads[b] = n;
        }
        if n != NONE {
            self.prev[n as usize] = p;
        }
    }

    /// Calls `visit` once for every point whose cell overlaps the box [min, max]
    /// (a superset of the points inside the box; callers test exactly).
    pub fn query_box(&self, min: &Vec3, max: &Vec3, mut visit: impl FnMut(u32)) {
        let lo = self.cell_of(min);
        let hi = self.cell_of(max);
        let span = |k: usize| (i64::from(hi[k]) - i64::from(lo[k]) + 1).max(0) as u64;
        let cells = span(0).saturating_mul(span(1)).saturating_mul(span(2));
        if cells == 0 {
            return;
        }
        let in_range = |c: &[i32; 3]| (0..3).all(|k| c[k] >= lo[k] && c[k] <= hi[k]);
        if cells > self.heads.len() as u64 {
            // A box bigger than the table: a linear pass is cheaper than the cells.
            for (i, present) in self.present.iter().enumerate() {
                if *present && in_range(&self.cell[i]) {
                    visit(i as u32);
                }
            }
            return;
        }
        for x in lo[0]..=hi[0] {
            for y in lo[1]..=hi[1] {
                for z in lo[2]..=hi[2] {
                    let c = [x, y, z];
                    let mut id = self.heads[self.bucket(c)];
                    while id != NONE {
                        // Different cells can share a bucket: keep only this cell's points,
                        // so each point is visited exactly once.
                        if self.cell[id as usize] == c {
                            visit(id);
                        }
                        id = self.next[id as usize];
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn query_returns_each_point_in_box_once() {
        let mut grid = PointGrid::new(0.1, 16);
        let pts: Vec<Vec3> = (0..1000).map(|i| Vec3::new((i % 10) as f64 * 0.05, (i / 10 % 10) as f64 * 0.05, (i / 100) as f64 * 0.05)).collect();
        for (i, p) in pts.iter().enumerate() {
            grid.insert(i as u32, p);
        }
        let (min, max) = (Vec3::new(0.1, 0.1, 0.1), Vec3::new(0.2, 0.3, 0.2));
        let mut found = Vec::new();
        grid.query_box(&min, &max, |id| found.push(id));
        let mut sorted = found.clone();
        sorted.sort();
        sorted.dedup();
        assert_eq!(sorted.len(), found.len(), "duplicates");
        for (i, p) in pts.iter().enumerate() {
            let inside = (0..3).all(|k| p[k] >= min[k] && p[k] <= max[k]);
            if inside {
                assert!(found.contains(&(i as u32)), "missing {i}");
            }
        }
    }

    #[test]
    fn floor_matches_std() {
        for v in [-2.5, -2.0, -0.1, 0.0, 0.1, 1.0, 1.9, 1e12, -1e12, f64::NAN] {
            let expected = if v.is_nan() { 0 } else { v.floor() as i32 };
            assert_eq!(floor_i32(v), expected, "{v}");
        }
    }

    #[test]
    fn moved_and_removed_points_follow() {
        let mut grid = PointGrid::new(1.0, 2);
        grid.insert(0, &Vec3::new(0.5, 0.5, 0.5));
        grid.insert(1, &Vec3::new(0.6, 0.5, 0.5));
        grid.update(0, &Vec3::new(5.5, 0.5, 0.5));
        let mut near = Vec::new();
        grid.query_box(&Vec3::zeros(), &Vec3::repeat(0.9), |id| near.push(id));
        assert_eq!(near, vec![1]);
        grid.remove(1);
        near.clear();
        grid.query_box(&Vec3::zeros(), &Vec3::repeat(10.0), |id| near.push(id));
        assert_eq!(near, vec![0]);
        assert_eq!(grid.len(), 1);
    }
}
