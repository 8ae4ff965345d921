//! One body's coupling over the unknowns: its columns of J and Δt·M_S⁻¹.

use crate::geometry::grid::NONE;

/// One body's coupling over the unknowns: the non-zero columns of J and Δt·M_S⁻¹.
#[derive(Clone, Debug)]
pub struct BodyCoupling {
    /// Unknowns the body touches.
    pub rows: Vec<u32>,
    /// Column of J for each of those rows.
    pub j: Vec<[f64; 6]>,
    /// Δt·M_S⁻¹, row-major.
    pub dt_minv: [[f64; 6]; 6],
}

impl BodyCoupling {
    /// Keeps the J columns of cells that are unknowns.
    pub fn new(
        row_of_cell: &[u32],
        jac: &[(usize, [f64; 6])],
        dt_minv: [[f64; 6]; 6],
    ) -> BodyCoupling {
        let (rows, j) = jac
            .iter()
            .filter(|(c, _)| row_of_cell[*c] != NONE)
            .map(|(c, col)| (row_of_cell[*c], *col))
            .unzip();
        BodyCoupling { rows, j, dt_minv }
    }

    /// J·x: the generalised force of a pressure field (force, torque).
    pub fn force(&self, x: &[f64]) -> [f64; 6] {
        let mut t = [0.0; 6];
        for (r, col) in self.rows.iter().zip(&self.j) {
            let xr = x[*r as usize];
            for d in 0..6 {
                t[d] += col[d] * xr;
            }
        }
        t
    }

    /// Δt·M⁻¹·f.
    pub fn dt_minv_times(&self, f: &[f64; 6]) -> [f64; 6] {
        let mut s = [0.0; 6];
        for r in 0..6 {
            for c in 0..6 {
                s[r] += self.dt_minv[r][c] * f[c];
            }
        }
        s
    }

    /// y += J ᵀ·s.
    pub fn add_jt(&self, s: &[f64; 6], y: &mut [f64]) {
        for (r, col) in self.rows.iter().zip(&self.j) {
            y[*r as usize] += (0..6).map(|d| col[d] * s[d]).sum::<f64>();
        }
    }
}
