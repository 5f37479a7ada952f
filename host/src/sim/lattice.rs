//! The paper's calibration lattice (section 4.3.1): a cube of
//! `cells_per_axis`^3 cubic cells over a volume of the room (tracker) frame,
//! and the order in which they are sampled. One definition for the
//! simulator's lattice sessions ([`super::simulate_session`]) and for the
//! live protocol (`spidar collect`, [`crate::procedures::collect`]).
//!
//! Order: "starting at the front of the volume, processing through the same
//! x-z plane and then moving forward to the next plane": plane by plane from
//! the front (`-y`) to the back; within an x-z plane, rows along x. Rows
//! alternate direction and planes alternate between bottom-up and top-down,
//! so that consecutive cells always share a face (the path a user naturally
//! takes).

use spidar_core::model::Vec3;

/// A lattice parameter that cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("lattice: `{field}`: {problem}")]
pub struct LatticeError {
    pub field: &'static str,
    pub problem: String,
}

/// A cube of `n^3` cubic cells, room frame, mm. Cell `[ix, iy, iz]` spans
/// `lo + i * edge .. lo + (i + 1) * edge` per axis, `lo = centre - size / 2`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lattice {
    centre_mm: Vec3<f64>,
    size_mm: f64,
    cells_per_axis: u32,
}

impl Lattice {
    /// Largest `cells_per_axis` accepted (10^9 cells).
    pub const MAX_CELLS_PER_AXIS: u32 = 1000;

    /// `cells_per_axis`^3 cells over the cube of edge `size_mm` centred on
    /// `centre_mm` (room frame).
    pub fn new(
        centre_mm: Vec3<f64>,
        size_mm: f64,
        cells_per_axis: u32,
    ) -> Result<Lattice, LatticeError> {
        if !centre_mm.iter().all(|v| v.is_finite()) {
            return Err(LatticeError {
                field: "centre_mm",
                problem: format!("{centre_mm:?} is not a finite point"),
            });
        }
        if !(size_mm.is_finite() && size_mm > 0.0) {
            return Err(LatticeError {
                field: "size_mm",
                problem: format!("{size_mm} is not a finite edge > 0"),
            });
        }
        if cells_per_axis == 0 || cells_per_axis > Self::MAX_CELLS_PER_AXIS {
            return Err(LatticeError {
                field: "cells_per_axis",
                problem: format!(
                    "{cells_per_axis} is not in 1..={}",
                    Self::MAX_CELLS_PER_AXIS
                ),
            });
        }
        Ok(Lattice {
            centre_mm,
            size_mm,
            cells_per_axis,
        })
    }

    /// The paper's lattice: 13^3 = 2197 cells over a 1 m cube.
    pub fn paper(centre_mm: Vec3<f64>) -> Result<Lattice, LatticeError> {
        Lattice::new(centre_mm, 1000.0, 13)
    }

    pub fn centre_mm(&self) -> Vec3<f64> {
        self.centre_mm
    }

    pub fn size_mm(&self) -> f64 {
        self.size_mm
    }

    pub fn cells_per_axis(&self) -> u32 {
        self.cells_per_axis
    }

    /// Edge of one cell, mm.
    pub fn cell_mm(&self) -> f64 {
        self.size_mm / f64::from(self.cells_per_axis)
    }

    /// Number of cells.
    pub fn len(&self) -> usize {
        (self.cells_per_axis as usize).pow(3)
    }

    /// Never true (a lattice has at least one cell); for clippy's sake.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Lowest corner of the cube.
    fn low_corner(&self) -> Vec3<f64> {
        core::array::from_fn(|k| self.centre_mm[k] - self.size_mm / 2.0)
    }

    /// The cells in sampling order (see the module documentation).
    pub fn order(&self) -> Vec<[u32; 3]> {
        let n = self.cells_per_axis;
        let mut cells = Vec::with_capacity(self.len());
        let mut x_forward = true;
        for iy in 0..n {
            for kz in 0..n {
                let iz = if iy % 2 == 0 { kz } else { n - 1 - kz };
                for kx in 0..n {
                    let ix = if x_forward { kx } else { n - 1 - kx };
                    cells.push([ix, iy, iz]);
                }
                x_forward = !x_forward;
            }
        }
        cells
    }

    /// Lowest and highest corner of `cell`, mm.
    pub fn bounds(&self, cell: [u32; 3]) -> (Vec3<f64>, Vec3<f64>) {
        let lo0 = self.low_corner();
        let edge = self.cell_mm();
        let lo: Vec3<f64> = core::array::from_fn(|k| lo0[k] + f64::from(cell[k]) * edge);
        let hi: Vec3<f64> = core::array::from_fn(|k| lo[k] + edge);
        (lo, hi)
    }

    /// Centre of `cell`, mm.
    pub fn cell_centre(&self, cell: [u32; 3]) -> Vec3<f64> {
        let (lo, _) = self.bounds(cell);
        let edge = self.cell_mm();
        core::array::from_fn(|k| lo[k] + edge * 0.5)
    }

    /// True if `p` lies in `cell` (faces included).
    pub fn contains(&self, cell: [u32; 3], p: &Vec3<f64>) -> bool {
        let (lo, hi) = self.bounds(cell);
        (0..3).all(|k| lo[k] <= p[k] && p[k] <= hi[k])
    }

    /// Distance from `p` to `cell` (0 inside), mm.
    pub fn distance_to(&self, cell: [u32; 3], p: &Vec3<f64>) -> f64 {
        let (lo, hi) = self.bounds(cell);
        (0..3)
            .map(|k| (lo[k] - p[k]).max(p[k] - hi[k]).max(0.0).powi(2))
            .sum::<f64>()
            .sqrt()
    }

    /// Every cell that [`Lattice::contains`] `p`: one inside a cell, up to
    /// eight on shared faces, edges and corners, none outside the cube.
    pub fn cells_containing(&self, p: &Vec3<f64>) -> Vec<[u32; 3]> {
        let lo0 = self.low_corner();
        let edge = self.cell_mm();
        let n = i64::from(self.cells_per_axis);
        let mut guess = [0i64; 3];
        for k in 0..3 {
            let g = ((p[k] - lo0[k]) / edge).floor();
            if !g.is_finite() || g < -1.0 || g > n as f64 {
                return Vec::new();
            }
            guess[k] = g as i64;
        }
        let mut out = Vec::new();
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    let c = [guess[0] + dx, guess[1] + dy, guess[2] + dz];
                    if c.iter().any(|&i| i < 0 || i >= n) {
                        continue;
                    }
                    let cell = c.map(|i| i as u32);
                    if self.contains(cell, p) {
                        out.push(cell);
                    }
                }
            }
        }
        out
    }

    /// Where `cell` comes in [`Lattice::order`] (None outside the lattice).
    pub fn index_of(&self, cell: [u32; 3]) -> Option<usize> {
        let n = self.cells_per_axis;
        if cell.iter().any(|&i| i >= n) {
            return None;
        }
        let (n, [ix, iy, iz]) = (n as usize, cell.map(|i| i as usize));
        // Rows before this one: iy planes of n rows, then the rows of this
        // plane before iz (planes alternate bottom-up / top-down).
        let kz = if iy % 2 == 0 { iz } else { n - 1 - iz };
        let row = iy * n + kz;
        // Rows alternate direction, continuing across planes.
        let kx = if row % 2 == 0 { ix } else { n - 1 - ix };
        Some(row * n + kx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_order_starts_at_the_front_and_walks_face_to_face() {
        let l = Lattice::new([0.0, 0.0, 0.0], 300.0, 3).unwrap();
        let order = l.order();
        assert_eq!(order.len(), 27);
        // Front plane (iy = 0) first, bottom row first, along x.
        assert_eq!(&order[..4], &[[0, 0, 0], [1, 0, 0], [2, 0, 0], [2, 0, 1]]);
        assert!(order[..9].iter().all(|c| c[1] == 0));
        assert!(order[9..18].iter().all(|c| c[1] == 1));
        assert!(order[18..].iter().all(|c| c[1] == 2));
        // Every cell once, each next to the previous one.
        let mut seen = std::collections::HashSet::new();
        for (k, c) in order.iter().enumerate() {
            assert!(seen.insert(*c), "{c:?} twice");
            assert_eq!(l.index_of(*c), Some(k));
            if k > 0 {
                let p = order[k - 1];
                let steps: u32 = (0..3).map(|a| p[a].abs_diff(c[a])).sum();
                assert_eq!(steps, 1, "{p:?} -> {c:?}");
            }
        }
        assert_eq!(l.index_of([3, 0, 0]), None);
        let paper = Lattice::paper([0.0; 3]).unwrap();
        for (k, c) in paper.order().iter().enumerate() {
            assert_eq!(paper.index_of(*c), Some(k));
        }
        assert_eq!(paper.len(), 2197);
    }

    #[test]
    fn cells_cover_the_cube_and_a_point_finds_its_cell() {
        let l = Lattice::new([10.0, -20.0, 1000.0], 300.0, 3).unwrap();
        assert_eq!(l.cell_mm(), 100.0);
        assert_eq!(l.cell_centre([1, 1, 1]), [10.0, -20.0, 1000.0]);
        assert_eq!(l.cell_centre([0, 0, 0]), [-90.0, -120.0, 900.0]);
        let (lo, hi) = l.bounds([2, 0, 1]);
        assert_eq!((lo, hi), ([60.0, -170.0, 950.0], [160.0, -70.0, 1050.0]));
        assert_eq!(
            l.cells_containing(&[100.0, -100.0, 1000.0]),
            vec![[2, 0, 1]]
        );
        assert!(l.contains([2, 0, 1], &[100.0, -100.0, 1000.0]));
        assert!(!l.contains([1, 0, 1], &[100.0, -100.0, 1000.0]));
        assert_eq!(l.distance_to([2, 0, 1], &[100.0, -100.0, 1000.0]), 0.0);
        assert_eq!(l.distance_to([2, 0, 1], &[100.0, -100.0, 1053.0]), 3.0);
        // A shared face belongs to both cells.
        let mut on_face = l.cells_containing(&[60.0, -100.0, 1000.0]);
        on_face.sort();
        assert_eq!(on_face, vec![[1, 0, 1], [2, 0, 1]]);
        // The cube's corner, and outside.
        assert_eq!(l.cells_containing(&[160.0, 130.0, 1150.0]), vec![[2, 2, 2]]);
        assert!(l.cells_containing(&[160.1, 0.0, 1000.0]).is_empty());
        assert!(l.cells_containing(&[f64::NAN, 0.0, 1000.0]).is_empty());
        assert!(l.cells_containing(&[1e300, 0.0, 1000.0]).is_empty());
    }

    #[test]
    fn bad_parameters_are_named() {
        let e = Lattice::new([0.0; 3], 0.0, 13).unwrap_err();
        assert_eq!(e.field, "size_mm");
        let e = Lattice::new([0.0; 3], 100.0, 0).unwrap_err();
        assert_eq!(e.field, "cells_per_axis");
        let e = Lattice::new([0.0, f64::NAN, 0.0], 100.0, 3).unwrap_err();
        assert!(e.to_string().contains("centre_mm"), "{e}");
    }
}
