//! Disjoint sets over `0..n`: connected pieces of meshes and grids, node classes at a
//! grid point. Path halving; the smaller root always wins a union, so roots (and
//! anything ordered by them) do not depend on the order of the unions.

#[derive(Debug, Clone)]
pub struct UnionFind {
    parent: Vec<u32>,
}

impl UnionFind {
    pub fn new(n: usize) -> Self {
        Self { parent: (0..n as u32).collect() }
    }

    pub fn find(&mut self, i: usize) -> usize {
        let mut i = i as u32;
        while self.parent[i as usize] != i {
            self.parent[i as usize] = self.parent[self.parent[i as usize] as usize];
            i = self.parent[i as usize];
        }
        i as usize
    }

    /// Joins the sets of `a` and `b`.
    pub fn union(&mut self, a: usize, b: usize) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra != rb {
            self.parent[ra.max(rb)] = ra.min(rb) as u32;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unions_join_sets_and_the_smallest_member_is_the_root() {
        let mut u = UnionFind::new(6);
        u.union(4, 2);
        u.union(5, 4);
        u.union(1, 3);
        assert_eq!(u.find(5), 2);
        assert_eq!(u.find(3), 1);
        assert_ne!(u.find(0), u.find(1));
        let roots: std::collections::BTreeSet<usize> = (0..6).map(|i| u.find(i)).collect();
        assert_eq!(roots.len(), 3);
    }
}
