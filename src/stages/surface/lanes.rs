//! The soft minimum's sum of terms c_p e^{−|x − x_p|/τ} over a run of points, four points
//! at a time on a processor with AVX2 and FMA (checked once, at run time), one at a time
//! elsewhere. The four-lane sum computes every point's term without a branch (a point beyond
//! the reach gets c_p = 0) and its own exponential (a degree-13 Taylor polynomial after
//! Cody and Waite's reduction by ln 2, within an ulp of the C library's); it adds the same
//! terms in another order, so the two agree to rounding.

use crate::math::Vec3;
use rayon::prelude::*;

/// Points as three arrays of coordinates, for sums four points at a time.
#[derive(Clone, Debug, Default)]
pub(super) struct Points {
    x: Vec<f64>,
    y: Vec<f64>,
    z: Vec<f64>,
}

impl Points {
    /// The points `at[i]` for `i` in `order`, in that order.
    pub(super) fn gather(order: &[u32], at: &[Vec3]) -> Points {
        let axis = |d: usize| order.par_iter().map(|&p| at[p as usize][d]).collect();
        Points { x: axis(0), y: axis(1), z: axis(2) }
    }

    /// Point `i`.
    #[cfg(test)]
    pub(super) fn get(&self, i: usize) -> Vec3 {
        Vec3::new(self.x[i], self.y[i], self.z[i])
    }
}

/// The cut-off and softness of the terms: c_p = (1 − d²/R²)³ for d² = |x − x_p|² < R², and
/// e^{−d/τ}.
#[derive(Clone, Copy, Debug)]
pub(super) struct Terms {
    /// 1/R².
    pub inv_r2: f64,
    /// 1/τ.
    pub inv_tau: f64,
    /// Whether this processor sums four points at a time.
    lanes: bool,
}

impl Terms {
    pub(super) fn new(inv_r2: f64, inv_tau: f64) -> Terms {
        Terms { inv_r2, inv_tau, lanes: has_lanes() }
    }

    /// One point's term at squared distance `d2`: zero beyond the reach.
    #[inline(always)]
    pub(super) fn term(&self, d2: f64) -> f64 {
        let t = 1.0 - d2 * self.inv_r2;
        if t <= 0.0 {
            0.0
        } else {
            t * t * t * (-d2.sqrt() * self.inv_tau).exp()
        }
    }

    /// The sum of the terms of `points[range]` seen from `x`.
    #[inline]
    pub(super) fn sum(&self, points: &Points, range: std::ops::Range<usize>, x: Vec3) -> f64 {
        self.sum_runs(points, &[(range.start as u32, range.end as u32)], x)
    }

    /// The sum of the terms of the points in the runs `runs` (`start..end` each) seen from
    /// `x`.
    #[inline]
    pub(super) fn sum_runs(&self, points: &Points, runs: &[(u32, u32)], x: Vec3) -> f64 {
        #[cfg(target_arch = "x86_64")]
        if self.lanes {
            // SAFETY: `lanes` is set only where the processor has AVX2 and FMA.
            return unsafe { avx2::sum(self, points, runs, x) };
        }
        runs.iter().map(|&(a, b)| self.sum_one_by_one(points, a as usize..b as usize, x)).sum()
    }

    /// [`Terms::sum`] a point at a time (where there are no lanes, and to test them).
    pub(super) fn sum_one_by_one(
        &self,
        points: &Points,
        range: std::ops::Range<usize>,
        x: Vec3,
    ) -> f64 {
        let mut sum = 0.0;
        for i in range {
            let d = Vec3::new(points.x[i] - x.x, points.y[i] - x.y, points.z[i] - x.z);
            sum += self.term(d.length_squared());
        }
        sum
    }

    /// The soft minimum's adjoint through [`Terms::sum`]: adds −τ·g·∂(term of point i seen
    /// from `x`)/∂x_i = g·term·(u + 6τ/(R² t)·d) to (`bx[i]`, `by[i]`, `bz[i]`) for the points
    /// i of `points[range]` (the bars indexed from `range.start`), for d = x_i − x, u = d/|d|
    /// (zero at d = 0) and t = 1 − |d|²/R² (φ = −τ ln(sum) − r, so with g = φ̄/sum this is
    /// the point's share of φ̄). Four points at a time where [`Terms::sum`] is.
    #[inline]
    pub(super) fn add_gradients(
        &self,
        points: &Points,
        range: std::ops::Range<usize>,
        x: Vec3,
        g: f64,
        bar: [&mut [f64]; 3],
    ) {
        #[cfg(target_arch = "x86_64")]
        if self.lanes {
            // SAFETY: `lanes` is set only where the processor has AVX2 and FMA.
            return unsafe { avx2::add_gradients(self, points, range, x, g, bar) };
        }
        // A point at a time (where there are no lanes, and to test them).
        let [bx, by, bz] = bar;
        let first = range.start;
        for i in range {
            let d = Vec3::new(points.x[i] - x.x, points.y[i] - x.y, points.z[i] - x.z);
            let w = self.gradient_weight(d.length_squared(), g);
            bx[i - first] += w * d.x;
            by[i - first] += w * d.y;
            bz[i - first] += w * d.z;
        }
    }

    /// The w with −τ·g·∂(a term at squared distance `d2`)/∂x_i = w·d: g·term·(1/|d| +
    /// 6τ/(R² t)); zero beyond the reach.
    #[inline(always)]
    fn gradient_weight(&self, d2: f64, g: f64) -> f64 {
        let t = 1.0 - d2 * self.inv_r2;
        if t <= 0.0 {
            return 0.0;
        }
        let len = d2.sqrt();
        let term = t * t * t * (-len * self.inv_tau).exp();
        let unit = if len > 0.0 { 1.0 / len } else { 0.0 };
        g * term * (unit + 6.0 * self.inv_r2 / (self.inv_tau * t))
    }

    /// [`Terms::sum`] four points at a time, None without AVX2 and FMA.
    #[cfg(test)]
    pub(super) fn sum_in_lanes(
        &self,
        points: &Points,
        range: std::ops::Range<usize>,
        x: Vec3,
    ) -> Option<f64> {
        #[cfg(target_arch = "x86_64")]
        if has_lanes() {
            // SAFETY: checked just now.
            return Some(unsafe {
                avx2::sum(self, points, &[(range.start as u32, range.end as u32)], x)
            });
        }
        None
    }
}

/// Whether this processor has AVX2 and FMA.
fn has_lanes() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// e^y four lanes at a time for each `y` (clamped to at least −708), None without AVX2 and
/// FMA.
#[cfg(test)]
pub(super) fn exp_in_lanes(y: [f64; 4]) -> Option<[f64; 4]> {
    #[cfg(target_arch = "x86_64")]
    if has_lanes() {
        // SAFETY: checked just now.
        return Some(unsafe { avx2::exp4(y) });
    }
    None
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{Points, Terms};
    use crate::math::Vec3;
    use std::arch::x86_64::*;

    /// ln 2 in two parts, the first with its low 21 bits zero so that n·ln2_hi is exact for
    /// |n| < 2¹¹ (Cody and Waite; fdlibm's constants).
    const LN2_HI: f64 = f64::from_bits(0x3fe6_2e42_fee0_0000);
    const LN2_LO: f64 = f64::from_bits(0x3dea_39ef_3579_3c76);
    /// 1.5·2⁵²: added to an integral n of magnitude under 2⁵¹, it leaves n in the low bits.
    const SHIFTER: f64 = 6_755_399_441_055_744.0;

    /// e^y for y in [−708, 0] (y below is clamped): y = n ln 2 + r with |r| ≤ ½ ln 2, e^r
    /// by its Taylor polynomial to r¹³ (truncation under 5e-18), 2ⁿ by its exponent bits.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn exp(y: __m256d) -> __m256d {
        let y = _mm256_max_pd(y, _mm256_set1_pd(-708.0));
        let n = _mm256_round_pd::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(
            _mm256_mul_pd(y, _mm256_set1_pd(std::f64::consts::LOG2_E)),
        );
        let r = _mm256_fnmadd_pd(n, _mm256_set1_pd(LN2_HI), y);
        let r = _mm256_fnmadd_pd(n, _mm256_set1_pd(LN2_LO), r);
        // e^r = 1 + r + r² Σ r^k/(k + 2)! for k ≤ 11, the sum in Estrin's order (a chain of
        // four multiply–adds, not eleven: pairs in r, then in r², r⁴ and r⁸), the 1 added
        // last so that its rounding is the only one at full size.
        const C: [f64; 12] = [
            0.5,
            1.0 / 6.0,
            1.0 / 24.0,
            1.0 / 120.0,
            1.0 / 720.0,
            1.0 / 5_040.0,
            1.0 / 40_320.0,
            1.0 / 362_880.0,
            1.0 / 3_628_800.0,
            1.0 / 39_916_800.0,
            1.0 / 479_001_600.0,
            1.0 / 6_227_020_800.0,
        ];
        let c = |k: usize| _mm256_set1_pd(C[k]);
        let pair = |k: usize| _mm256_fmadd_pd(c(k + 1), r, c(k));
        let r2 = _mm256_mul_pd(r, r);
        let r4 = _mm256_mul_pd(r2, r2);
        let r8 = _mm256_mul_pd(r4, r4);
        let q0 = _mm256_fmadd_pd(pair(2), r2, pair(0));
        let q1 = _mm256_fmadd_pd(pair(6), r2, pair(4));
        let q2 = _mm256_fmadd_pd(pair(10), r2, pair(8));
        let tail = _mm256_fmadd_pd(q2, r8, _mm256_fmadd_pd(q1, r4, q0));
        let p = _mm256_add_pd(_mm256_set1_pd(1.0), _mm256_fmadd_pd(r2, tail, r));
        // 2ⁿ: n + 1023 (in [1, 1023]) into the exponent's bits.
        let biased = _mm256_add_pd(n, _mm256_set1_pd(SHIFTER + 1023.0));
        let two_n = _mm256_castsi256_pd(_mm256_slli_epi64::<52>(_mm256_castpd_si256(biased)));
        _mm256_mul_pd(p, two_n)
    }

    /// The terms of the points at (`px`, `py`, `pz`) seen from (`cx`, `cy`, `cz`).
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    #[allow(clippy::too_many_arguments)]
    unsafe fn terms(
        px: __m256d,
        py: __m256d,
        pz: __m256d,
        cx: __m256d,
        cy: __m256d,
        cz: __m256d,
        inv_r2: __m256d,
        inv_tau: __m256d,
    ) -> __m256d {
        let (dx, dy, dz) = (_mm256_sub_pd(px, cx), _mm256_sub_pd(py, cy), _mm256_sub_pd(pz, cz));
        let d2 = _mm256_fmadd_pd(dx, dx, _mm256_fmadd_pd(dy, dy, _mm256_mul_pd(dz, dz)));
        let t =
            _mm256_max_pd(_mm256_fnmadd_pd(d2, inv_r2, _mm256_set1_pd(1.0)), _mm256_setzero_pd());
        // Four points all beyond the reach (about a third of a block's are) add nothing.
        if _mm256_movemask_pd(_mm256_cmp_pd::<_CMP_GT_OQ>(t, _mm256_setzero_pd())) == 0 {
            return _mm256_setzero_pd();
        }
        let e = exp(_mm256_sub_pd(_mm256_setzero_pd(), _mm256_mul_pd(_mm256_sqrt_pd(d2), inv_tau)));
        _mm256_mul_pd(_mm256_mul_pd(_mm256_mul_pd(t, t), t), e)
    }

    /// [`Terms::sum_runs`] four points at a time.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn sum(
        terms_of: &Terms,
        points: &Points,
        runs: &[(u32, u32)],
        x: Vec3,
    ) -> f64 {
        let (xs, ys, zs) = (&points.x[..], &points.y[..], &points.z[..]);
        let len = xs.len();
        assert!(ys.len() == len && zs.len() == len);
        let (cx, cy, cz) = (_mm256_set1_pd(x.x), _mm256_set1_pd(x.y), _mm256_set1_pd(x.z));
        let inv_r2 = _mm256_set1_pd(terms_of.inv_r2);
        let inv_tau = _mm256_set1_pd(terms_of.inv_tau);
        let mut acc = _mm256_setzero_pd();
        for &(start, end) in runs {
            let (mut i, n) = (start as usize, end as usize);
            assert!(i <= n && n <= len);
            while i + 4 <= n {
                // SAFETY: i + 4 ≤ n ≤ the length of each array.
                let (px, py, pz) = unsafe {
                    (
                        _mm256_loadu_pd(xs.as_ptr().add(i)),
                        _mm256_loadu_pd(ys.as_ptr().add(i)),
                        _mm256_loadu_pd(zs.as_ptr().add(i)),
                    )
                };
                acc = _mm256_add_pd(acc, terms(px, py, pz, cx, cy, cz, inv_r2, inv_tau));
                i += 4;
            }
            if i < n {
                // The last one to three points: the lanes past the end load nothing and add 0.
                let left = _mm256_set1_epi64x((n - i) as i64);
                let mask = _mm256_cmpgt_epi64(left, _mm256_setr_epi64x(0, 1, 2, 3));
                // SAFETY: a masked load reads only the lanes whose mask is set, all below n.
                let (px, py, pz) = unsafe {
                    (
                        _mm256_maskload_pd(xs.as_ptr().add(i), mask),
                        _mm256_maskload_pd(ys.as_ptr().add(i), mask),
                        _mm256_maskload_pd(zs.as_ptr().add(i), mask),
                    )
                };
                let t = terms(px, py, pz, cx, cy, cz, inv_r2, inv_tau);
                acc = _mm256_add_pd(acc, _mm256_and_pd(t, _mm256_castsi256_pd(mask)));
            }
        }
        let mut lanes = [0.0; 4];
        // SAFETY: four f64 into an array of four.
        unsafe { _mm256_storeu_pd(lanes.as_mut_ptr(), acc) };
        (lanes[0] + lanes[1]) + (lanes[2] + lanes[3])
    }

    /// [`Terms::add_gradients`] four points at a time.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn add_gradients(
        terms_of: &Terms,
        points: &Points,
        range: std::ops::Range<usize>,
        x: Vec3,
        g: f64,
        bar: [&mut [f64]; 3],
    ) {
        let (xs, ys, zs) = (&points.x[..], &points.y[..], &points.z[..]);
        let (first, n) = (range.start, range.end);
        assert!(first <= n && n <= xs.len() && n <= ys.len() && n <= zs.len());
        let [bx, by, bz] = bar;
        assert!(bx.len() >= n - first && by.len() >= n - first && bz.len() >= n - first);
        let (cx, cy, cz) = (_mm256_set1_pd(x.x), _mm256_set1_pd(x.y), _mm256_set1_pd(x.z));
        let inv_r2 = _mm256_set1_pd(terms_of.inv_r2);
        let inv_tau = _mm256_set1_pd(terms_of.inv_tau);
        let six_tau_r2 = _mm256_set1_pd(6.0 * terms_of.inv_r2 / terms_of.inv_tau);
        let gs = _mm256_set1_pd(g);
        let (zero, one) = (_mm256_setzero_pd(), _mm256_set1_pd(1.0));
        let mut i = first;
        while i < n {
            // Four lanes, or the last one to three (the lanes past the end masked off).
            let left = _mm256_set1_epi64x((n - i) as i64);
            let live =
                _mm256_castsi256_pd(_mm256_cmpgt_epi64(left, _mm256_setr_epi64x(0, 1, 2, 3)));
            let mask = _mm256_castpd_si256(live);
            let o = i - first;
            // SAFETY: a masked load reads only the lanes whose mask is set, all below n.
            let (px, py, pz) = unsafe {
                (
                    _mm256_maskload_pd(xs.as_ptr().add(i), mask),
                    _mm256_maskload_pd(ys.as_ptr().add(i), mask),
                    _mm256_maskload_pd(zs.as_ptr().add(i), mask),
                )
            };
            let (dx, dy, dz) =
                (_mm256_sub_pd(px, cx), _mm256_sub_pd(py, cy), _mm256_sub_pd(pz, cz));
            let d2 = _mm256_fmadd_pd(dx, dx, _mm256_fmadd_pd(dy, dy, _mm256_mul_pd(dz, dz)));
            let t = _mm256_fnmadd_pd(d2, inv_r2, one);
            let inside = _mm256_and_pd(_mm256_cmp_pd::<_CMP_GT_OQ>(t, zero), live);
            i += 4;
            if _mm256_movemask_pd(inside) == 0 {
                continue;
            }
            let len = _mm256_sqrt_pd(d2);
            let e = exp(_mm256_sub_pd(zero, _mm256_mul_pd(len, inv_tau)));
            let term = _mm256_mul_pd(_mm256_mul_pd(_mm256_mul_pd(t, t), t), e);
            let unit =
                _mm256_and_pd(_mm256_div_pd(one, len), _mm256_cmp_pd::<_CMP_GT_OQ>(len, zero));
            let w = _mm256_mul_pd(
                _mm256_mul_pd(gs, term),
                _mm256_add_pd(unit, _mm256_div_pd(six_tau_r2, t)),
            );
            // Lanes beyond the reach (or the end) divide by t ≤ 0: masked to zero.
            let w = _mm256_and_pd(w, inside);
            // SAFETY: the masked loads and stores touch only lanes below n − first.
            unsafe {
                for (b, d) in [(&mut *bx, dx), (&mut *by, dy), (&mut *bz, dz)] {
                    let at = b.as_mut_ptr().add(o);
                    let sum = _mm256_fmadd_pd(w, d, _mm256_maskload_pd(at, mask));
                    _mm256_maskstore_pd(at, mask, sum);
                }
            }
        }
    }

    /// [`exp`] of four values, for the tests.
    #[cfg(test)]
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn exp4(y: [f64; 4]) -> [f64; 4] {
        let mut out = [0.0; 4];
        // SAFETY: four f64 from and into arrays of four.
        unsafe { _mm256_storeu_pd(out.as_mut_ptr(), exp(_mm256_loadu_pd(y.as_ptr()))) };
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic values in [0, 1).
    fn uniform(n: usize, seed: u64) -> Vec<f64> {
        let mut s = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (0..n)
            .map(|_| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (s >> 11) as f64 / (1u64 << 53) as f64
            })
            .collect()
    }

    /// The lanes' exponential is within an ulp of the C library's over [−708, 0], the range
    /// a term reads (the lanes clamp below it), and exact at 0.
    #[test]
    fn the_lanes_exponential_matches_the_library() {
        let Some(at_zero) = exp_in_lanes([0.0, -708.0, -750.0, -1e-300]) else {
            eprintln!("no AVX2 and FMA here: the lanes are not used");
            return;
        };
        assert_eq!(at_zero[0], 1.0);
        assert_eq!(at_zero[2], at_zero[1], "below −708 the lanes clamp");
        let mut worst: f64 = 0.0;
        let u = uniform(400_000, 7);
        for (k, chunk) in u.chunks(4).enumerate() {
            // Half the values in a term's usual range (−R/τ ≈ −5.7 and up), half over all.
            let scale = if k % 2 == 0 { 8.0 } else { 708.0 };
            let y = [0, 1, 2, 3].map(|i| -chunk[i] * scale);
            let e = exp_in_lanes(y).unwrap();
            for i in 0..4 {
                let want = y[i].exp();
                worst = worst.max((e[i] - want).abs() / (want * f64::EPSILON));
            }
        }
        eprintln!("worst: {worst:.2} ulp");
        assert!(worst <= 1.0, "{worst} ulp");
    }

    /// Four points at a time give the sum a point at a time gives, to rounding, for runs of
    /// every length up to 13 (each tail of one to three) and centres with points inside and
    /// beyond the reach.
    #[test]
    fn the_lanes_sum_the_terms_one_by_one_sums() {
        let n = 400;
        let u = uniform(3 * n, 3);
        let at: Vec<Vec3> =
            (0..n).map(|i| Vec3::new(u[3 * i], u[3 * i + 1], u[3 * i + 2]) * 0.5).collect();
        let order: Vec<u32> = (0..n as u32).rev().collect();
        let points = Points::gather(&order, &at);
        assert_eq!(points.get(0), at[n - 1]);
        // R = 0.2, τ = 0.035: a cell of 0.1 and the defaults.
        let terms = Terms::new(1.0 / 0.04, 1.0 / 0.035);
        let mut checked = 0;
        let mut worst: f64 = 0.0;
        for start in 0..40 {
            for len in 0..=13 {
                for x in [Vec3::splat(0.25), Vec3::new(0.1, 0.3, 0.2), Vec3::splat(0.6)] {
                    let range = 7 * start..7 * start + len;
                    let one = terms.sum_one_by_one(&points, range.clone(), x);
                    let Some(four) = terms.sum_in_lanes(&points, range, x) else {
                        eprintln!("no AVX2 and FMA here: the lanes are not used");
                        return;
                    };
                    if one == 0.0 {
                        assert_eq!(four, 0.0);
                        continue;
                    }
                    checked += 1;
                    // What rounding allows: d² is rounded differently (with and without FMA,
                    // a few ε relative), and a term near the reach, where t = 1 − d²/R² is
                    // small, reads that rounding 3d²/(R²t) times over (and e^{−d/τ}
                    // d/(2τ) times); each exponential is within an ulp or two.
                    let allowed: f64 = (7 * start..7 * start + len)
                        .map(|i| {
                            let d2 = (points.get(i) - x).length_squared();
                            let t = 1.0 - d2 * terms.inv_r2;
                            let gain =
                                3.0 * d2 * terms.inv_r2 / t + 0.5 * d2.sqrt() * terms.inv_tau;
                            terms.term(d2) * f64::EPSILON * (8.0 + 4.0 * gain)
                        })
                        .sum();
                    worst = worst.max((four - one).abs() / allowed);
                }
            }
        }
        eprintln!("{checked} sums, worst difference {worst:.3} of what rounding allows");
        assert!(checked > 700, "{checked}");
        assert!(worst <= 1.0, "{worst}");
    }

    /// The gradients four points at a time are those a point at a time gives, to rounding,
    /// for runs of every length up to 13 and centres with points inside and beyond the
    /// reach (one at a centre); and a point at a time they are the terms' derivatives
    /// (central differences of [`Terms::term`]).
    #[test]
    fn the_lanes_gradients_match_one_by_one_and_the_terms_derivatives() {
        let n = 400;
        let u = uniform(3 * n, 5);
        let mut at: Vec<Vec3> =
            (0..n).map(|i| Vec3::new(u[3 * i], u[3 * i + 1], u[3 * i + 2]) * 0.5).collect();
        at[8] = Vec3::splat(0.25);
        let order: Vec<u32> = (0..n as u32).collect();
        let points = Points::gather(&order, &at);
        let terms = Terms::new(1.0 / 0.04, 1.0 / 0.035);
        // The same terms a point at a time.
        let one_by_one = Terms { lanes: false, ..terms };
        let g = -1.7;
        // One by one against the derivatives of the terms.
        let x = Vec3::new(0.22, 0.27, 0.24);
        let mut bar = [vec![0.0; 40], vec![0.0; 40], vec![0.0; 40]];
        let [bx, by, bz] = &mut bar;
        one_by_one.add_gradients(&points, 0..40, x, g, [bx, by, bz]);
        let mut inside = 0;
        for i in 0..40 {
            let h = 1e-7;
            let fd = Vec3::from_array([0, 1, 2].map(|a| {
                let e = h * crate::math::unit(a);
                let term = |p: Vec3| terms.term((p - x).length_squared());
                g * (term(at[i] + e) - term(at[i] - e)) / (2.0 * h)
            }));
            // What is added is −τ·g·∂term (φ = −τ ln(sum) − r).
            let got = Vec3::new(bar[0][i], bar[1][i], bar[2][i]) * (-terms.inv_tau);
            inside += usize::from(got != Vec3::ZERO);
            assert!((got - fd).length() <= 1e-6 * (1.0 + fd.length()), "{i}: {got} against {fd}");
        }
        assert!(inside > 5, "{inside} of 40 points within the reach");
        if !terms.lanes {
            eprintln!("no AVX2 and FMA here: the lanes are not used");
            return;
        }
        let mut worst: f64 = 0.0;
        for start in 0..40 {
            for len in 0..=13 {
                for x in [Vec3::splat(0.25), Vec3::new(0.1, 0.3, 0.2), Vec3::splat(0.6)] {
                    let range = 7 * start..7 * start + len;
                    let mut one = [vec![0.0; len], vec![0.0; len], vec![0.0; len]];
                    let [ox, oy, oz] = &mut one;
                    one_by_one.add_gradients(&points, range.clone(), x, g, [ox, oy, oz]);
                    let mut four = [vec![0.0; len], vec![0.0; len], vec![0.0; len]];
                    let [fx, fy, fz] = &mut four;
                    terms.add_gradients(&points, range.clone(), x, g, [fx, fy, fz]);
                    for i in 0..len {
                        let a = Vec3::new(one[0][i], one[1][i], one[2][i]);
                        let b = Vec3::new(four[0][i], four[1][i], four[2][i]);
                        if a == Vec3::ZERO {
                            assert_eq!(b, Vec3::ZERO);
                            continue;
                        }
                        // As for the sums: d² and t rounded differently read 3d²/(R²t)
                        // and d/(2τ) times over, and 1/t once more in the weight.
                        let d2 = (points.get(range.start + i) - x).length_squared();
                        let t = 1.0 - d2 * terms.inv_r2;
                        let gain = 4.0 * d2 * terms.inv_r2 / t + 0.5 * d2.sqrt() * terms.inv_tau;
                        let allowed = a.length() * f64::EPSILON * (16.0 + 4.0 * gain);
                        worst = worst.max((a - b).length() / allowed);
                    }
                }
            }
        }
        eprintln!("worst difference {worst:.3} of what rounding allows");
        assert!(worst <= 1.0, "{worst}");
    }
}
