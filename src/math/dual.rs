//! Forward-mode dual numbers: a value and its derivatives in N directions. The face
//! fraction code is generic over [`Scalar`], so the same code gives a fraction (f64) and
//! its derivative with respect to a body's pose (`Dual<6>`), with identical values.

use std::ops::{Add, Div, Mul, Neg, Sub};

/// What the generic geometry code needs of a number.
pub trait Scalar:
    Copy
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
{
    /// The value.
    fn val(self) -> f64;
    /// A constant.
    fn cst(x: f64) -> Self;
    /// |x|.
    fn abs(self) -> Self {
        if self.val() < 0.0 {
            -self
        } else {
            self
        }
    }
}

impl Scalar for f64 {
    #[inline]
    fn val(self) -> f64 {
        self
    }
    #[inline]
    fn cst(x: f64) -> f64 {
        x
    }
    #[inline]
    fn abs(self) -> f64 {
        f64::abs(self)
    }
}

/// A value with derivatives in N directions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Dual<const N: usize> {
    /// Value.
    pub v: f64,
    /// Derivatives.
    pub d: [f64; N],
}

impl<const N: usize> Dual<N> {
    /// A value with the given derivatives.
    pub fn new(v: f64, d: [f64; N]) -> Self {
        Dual { v, d }
    }
}

impl<const N: usize> Add for Dual<N> {
    type Output = Self;
    #[inline]
    fn add(self, o: Self) -> Self {
        Dual { v: self.v + o.v, d: std::array::from_fn(|i| self.d[i] + o.d[i]) }
    }
}

impl<const N: usize> Sub for Dual<N> {
    type Output = Self;
    #[inline]
    fn sub(self, o: Self) -> Self {
        Dual { v: self.v - o.v, d: std::array::from_fn(|i| self.d[i] - o.d[i]) }
    }
}

impl<const N: usize> Mul for Dual<N> {
    type Output = Self;
    // The product rule adds.
    #[allow(clippy::suspicious_arithmetic_impl)]
    #[inline]
    fn mul(self, o: Self) -> Self {
        Dual { v: self.v * o.v, d: std::array::from_fn(|i| self.d[i] * o.v + self.v * o.d[i]) }
    }
}

impl<const N: usize> Div for Dual<N> {
    type Output = Self;
    #[inline]
    fn div(self, o: Self) -> Self {
        let inv = 1.0 / o.v;
        let v = self.v / o.v;
        Dual { v, d: std::array::from_fn(|i| (self.d[i] - v * o.d[i]) * inv) }
    }
}

impl<const N: usize> Neg for Dual<N> {
    type Output = Self;
    #[inline]
    fn neg(self) -> Self {
        Dual { v: -self.v, d: self.d.map(|x| -x) }
    }
}

impl<const N: usize> Scalar for Dual<N> {
    #[inline]
    fn val(self) -> f64 {
        self.v
    }
    #[inline]
    fn cst(x: f64) -> Self {
        Dual { v: x, d: [0.0; N] }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quotient_rule() {
        let x = Dual::new(2.0, [1.0, 0.0]);
        let y = Dual::new(3.0, [0.0, 1.0]);
        let q = (x * x) / y; // x²/y: ∂x = 2x/y, ∂y = −x²/y²
        assert!((q.v - 4.0 / 3.0).abs() < 1e-15);
        assert!((q.d[0] - 4.0 / 3.0).abs() < 1e-15 && (q.d[1] + 4.0 / 9.0).abs() < 1e-15);
    }
}
