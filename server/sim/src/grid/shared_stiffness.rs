//! The elements' single-precision stiffnesses as the solver reads them, each distinct
//! matrix stored once.
//!
//! Every step rotates every moving element's stiffness (`solver::kernels::
//! rotate_and_multiply`), 2.3 KB a matrix in the planar layout. Stored per element, a
//! level-0 body streams all of them through the caches each step (5.9 MB on the
//! 3,321-node cantilever of the MuJoCo comparison, as much as its Cholesky factor in
//! bfloat16): perf put a quarter of the rotation's samples on loading them. But at level
//! 0 an element is one voxel, so its matrix is the voxel's of its material (plus the
//! ghost): a body of one material has a single distinct matrix, the layered abdomen a
//! handful; coarse levels' condensed elements differ from each other, and there each
//! stays its own. So elements point into a table of distinct matrices, found by their
//! bits (equal bits, one entry; the solver computes with the same values, so the same
//! state hash), with a count of the elements using each: a cut that changes an element's
//! matrix gives it another entry and frees the old one when no element uses it any more,
//! so the table holds at most one entry per element however many cuts a session makes.

use std::collections::HashMap;

use crate::solver::kernels::Planar24;

/// The table: `matrices[of_element[e]]` is element e's stiffness.
#[derive(Debug, Clone, Default)]
pub struct SharedStiffness {
    matrices: Vec<Planar24>,
    /// Per entry, how many elements use it (0: a free entry, listed in `free`).
    users: Vec<u32>,
    free: Vec<u32>,
    /// Entries by a hash of their bits (then compared whole).
    by_bits: HashMap<u64, Vec<u32>>,
    of_element: Vec<u32>,
}

impl SharedStiffness {
    /// Adds an element with stiffness `k`.
    pub fn push(&mut self, k: &Planar24) {
        let entry = self.entry_for(k);
        self.of_element.push(entry);
    }

    /// Replaces element `e`'s stiffness with `k`.
    pub fn set(&mut self, e: usize, k: &Planar24) {
        let old = self.of_element[e];
        if same_bits(&self.matrices[old as usize], k) {
            return;
        }
        // Released first, so that an entry only this element used is the one reused.
        self.release(old);
        self.of_element[e] = self.entry_for(k);
    }

    /// The entry holding `k` with one more user (a new one where none holds it).
    fn entry_for(&mut self, k: &Planar24) -> u32 {
        let hash = bits_hash(k);
        let candidates = self.by_bits.entry(hash).or_default();
        if let Some(&found) = candidates.iter().find(|&&c| same_bits(&self.matrices[c as usize], k)) {
            self.users[found as usize] += 1;
            return found;
        }
        let entry = match self.free.pop() {
            Some(free) => {
                self.matrices[free as usize] = *k;
                self.users[free as usize] = 1;
                free
            }
            None => {
                self.matrices.push(*k);
                self.users.push(1);
                (self.matrices.len() - 1) as u32
            }
        };
        candidates.push(entry);
        entry
    }

    /// One user fewer for `entry`; freed when it has none.
    fn release(&mut self, entry: u32) {
        let users = &mut self.users[entry as usize];
        *users -= 1;
        if *users == 0 {
            let hash = bits_hash(&self.matrices[entry as usize]);
            let candidates = self.by_bits.get_mut(&hash).expect("an entry in use is indexed by its bits");
            candidates.retain(|&c| c != entry);
            if candidates.is_empty() {
                self.by_bits.remove(&hash);
            }
            self.free.push(entry);
        }
    }
}

impl std::ops::Index<usize> for SharedStiffness {
    type Output = Planar24;

    /// Element `e`'s stiffness.
    fn index(&self, e: usize) -> &Planar24 {
        &self.matrices[self.of_element[e] as usize]
    }
}

fn values(k: &Planar24) -> impl Iterator<Item = f32> + '_ {
    k.iter().flat_map(|row| row.iter().flat_map(|plane| plane.0.iter().copied()))
}

/// Equal bits (not equal values: −0 and 0 differ, and a NaN equals its own bits).
fn same_bits(a: &Planar24, b: &Planar24) -> bool {
    values(a).map(f32::to_bits).eq(values(b).map(f32::to_bits))
}

/// The state hash's FNV-1a over the bits: the same on every machine (only the table's
/// lookups use it, but no random seed is needed either).
fn bits_hash(k: &Planar24) -> u64 {
    let mut hasher = crate::hash::StateHasher::new();
    values(k).for_each(|v| hasher.write_f32(v));
    hasher.finish()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solver::kernels::F8;

    /// Distinct matrices in use.
    fn distinct(table: &SharedStiffness) -> usize {
        table.users.iter().filter(|&&u| u > 0).count()
    }

    fn matrix(seed: f32) -> Planar24 {
        std::array::from_fn(|r| std::array::from_fn(|l| F8(std::array::from_fn(|b| ((r * 24 + l * 8 + b) as f32 * 0.1 + seed).sin()))))
    }

    /// A body of one material at level 0 (and one of whole cells at level 1) has one
    /// distinct matrix, ghost material included; a cut gives the elements it changed
    /// their own, and never more entries than elements.
    #[test]
    fn a_uniform_body_shares_one_matrix_until_a_cut_changes_some() {
        use crate::grid::condense::{Volumetric, VoxelMatrices};
        use crate::grid::topology::{Layout, Topology};
        let volume = crate::volume::procedural::solid_box([0.008, 0.004, 0.004], 0.001, 1);
        for level in [0, 1] {
            let layout = Layout::new(volume.dims, level, volume.spacing_m);
            let material = volume.labels.iter().map(|&l| u16::from(l != 0)).collect();
            let mut topo = Topology::build(layout, material, VoxelMatrices::new(volume.spacing_m, &[(1e4, 0.45, 1000.0)], Volumetric::MeanDilatation));
            let ghost = topo.elements.stiffness[0] * 1e-3;
            topo.set_ghost(ghost);
            let table = &topo.elements.stiffness_single;
            assert_eq!((table.of_element.len(), distinct(table)), (topo.elements.len(), 1), "level {level}");
            // Two voxels of one corner cell go: at level 1 its element changes (and is
            // its own entry); at level 0 their elements die and the rest stay shared.
            topo.remove_voxels(&[0, 1]);
            let table = &topo.elements.stiffness_single;
            let live_distinct = (0..topo.elements.len()).filter(|&e| topo.elements.alive[e]).map(|e| table.of_element[e]).collect::<std::collections::BTreeSet<u32>>().len();
            assert_eq!(live_distinct, if level == 0 { 1 } else { 2 }, "level {level} after the cut");
            assert!(table.matrices.len() <= table.of_element.len());
        }
    }

    #[test]
    fn elements_with_equal_matrices_share_one_entry_and_read_back_their_own() {
        let (a, b) = (matrix(1.0), matrix(2.0));
        let mut table = SharedStiffness::default();
        for k in [&a, &b, &a, &a, &b] {
            table.push(k);
        }
        assert_eq!((table.of_element.len(), distinct(&table)), (5, 2));
        for (e, k) in [&a, &b, &a, &a, &b].into_iter().enumerate() {
            assert!(same_bits(&table[e], k), "element {e}");
        }
        // −0 and 0 are different bits: a matrix differing only there is its own entry.
        let mut c = a;
        c[0][0].0[0] = if a[0][0].0[0] == 0.0 { -0.0 } else { -a[0][0].0[0] };
        table.push(&c);
        assert_eq!(distinct(&table), 3);
    }

    #[test]
    fn a_changed_element_takes_another_entry_and_an_unused_one_is_reused() {
        let (a, b, c) = (matrix(1.0), matrix(2.0), matrix(3.0));
        let mut table = SharedStiffness::default();
        table.push(&a);
        table.push(&a);
        table.push(&b);
        // Element 2 alone used b: its entry is freed and taken by c, the table does not grow.
        table.set(2, &c);
        assert_eq!((distinct(&table), table.matrices.len()), (2, 2));
        assert!(same_bits(&table[2], &c) && same_bits(&table[0], &a) && same_bits(&table[1], &a));
        // Element 0 leaves a shared entry: a stays for element 1.
        table.set(0, &b);
        assert!(same_bits(&table[0], &b) && same_bits(&table[1], &a));
        assert_eq!((distinct(&table), table.matrices.len()), (3, 3));
        // Setting the same bits changes nothing; back to a shares element 1's entry.
        table.set(0, &b);
        table.set(0, &a);
        assert_eq!(distinct(&table), 2);
        assert_eq!(table.of_element[0], table.of_element[1]);
        assert!(same_bits(&table[0], &a) && same_bits(&table[2], &c));
    }
}
