//! Dense linear algebra through faer, behind plain non-generic functions on
//! row-major slices (faer is used only here: it crashes rustc in crates
//! built with the autodiff flag).

/// The thin SVD `A = U·diag(s)·Vᵀ` of a row-major `m × n` matrix: `u` is
/// `m × k` and `v` is `n × k` (row-major), `s` descending, `k = min(m, n)`.
#[derive(Clone, Debug, PartialEq)]
pub struct Svd {
    /// Left singular vectors, `m × k`.
    pub u: Vec<f64>,
    /// Singular values, descending.
    pub s: Vec<f64>,
    /// Right singular vectors, `n × k`.
    pub v: Vec<f64>,
}

/// Why an SVD failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SvdFailed;

/// The thin SVD of the row-major `m × n` matrix `a`.
///
/// # Panics
/// If `a.len() != m·n`.
pub fn svd(m: usize, n: usize, a: &[f64]) -> Result<Svd, SvdFailed> {
    assert_eq!(a.len(), m * n, "svd: the matrix has the wrong length");
    let d = faer::MatRef::from_row_major_slice(a, m, n).thin_svd().map_err(|_| SvdFailed)?;
    let k = m.min(n);
    let (uu, vv, ss) = (d.U(), d.V(), d.S().column_vector());
    let mut u = vec![0.0; m * k];
    let mut v = vec![0.0; n * k];
    for i in 0..m {
        for c in 0..k {
            u[i * k + c] = uu[(i, c)];
        }
    }
    for i in 0..n {
        for c in 0..k {
            v[i * k + c] = vv[(i, c)];
        }
    }
    let s: Vec<f64> = (0..k).map(|c| ss[c]).collect();
    Ok(Svd { u, s, v })
}

/// `x = V·diag(s⁻ᵝ)·Uᵀ·b` for the row-major `m × n` matrix `a`, singular
/// values at or below `truncation · s_max` (relative) left out: the
/// pseudo-inverse for `beta = 1`, the half-inverse of half-inverse
/// gradients for `beta = ½`. `b` has `m` values, the result `n`. By the
/// SVD in double precision ([`PowerMethod::SVD_F64`]).
pub fn pseudo_inverse_power_apply(m: usize, n: usize, a: &[f64], b: &[f64], beta: f64, truncation: f64) -> Result<Vec<f64>, SvdFailed> {
    pseudo_inverse_power_apply_with(m, n, a, b, beta, truncation, PowerMethod::SVD_F64)
}

/// How [`pseudo_inverse_power_apply_with`] decomposes the matrix.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Decomposition {
    /// The thin SVD of `A` itself.
    Svd,
    /// The symmetric eigendecomposition of the smaller Gram matrix (`A·Aᵀ`
    /// when `m ≤ n`, else `Aᵀ·A`), whose eigenvalues are `s²`: about
    /// `2·m²·n` flops for the product and `O(m³)` for the eigensolver
    /// against the SVD's larger constant, but it squares the condition
    /// number (see [`gram_is_accurate`]).
    Gram,
    /// The Gram route with its spectrum checked: when an eigenvalue it
    /// keeps lies below `ε·λ_max / GRAM_TOLERANCE`, where forming the Gram
    /// matrix may have moved it by more than [`GRAM_TOLERANCE`] relatively,
    /// the SVD is taken instead. As accurate as the SVD, and as fast as the
    /// Gram route whenever the kept spectrum allows it.
    Checked,
}

/// The decomposition and the precision it runs in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct PowerMethod {
    /// SVD or Gram eigendecomposition.
    pub decomposition: Decomposition,
    /// Decompose in `f32` (the published HIG code's precision) instead of
    /// `f64`; the products with `b` and the result stay in `f64`.
    pub single: bool,
}

impl PowerMethod {
    /// The SVD in `f64`: the reference.
    pub const SVD_F64: Self = Self { decomposition: Decomposition::Svd, single: false };
    /// The Gram eigendecomposition in `f64`.
    pub const GRAM_F64: Self = Self { decomposition: Decomposition::Gram, single: false };
    /// The SVD in `f32`, as the published code.
    pub const SVD_F32: Self = Self { decomposition: Decomposition::Svd, single: true };
    /// The checked Gram route in `f64` (the SVD where the Gram matrix
    /// cannot resolve the kept spectrum): the default.
    pub const AUTO: Self = Self { decomposition: Decomposition::Checked, single: false };
}

/// The largest relative error the Gram route may add to a kept component
/// (see [`gram_is_accurate`]).
pub const GRAM_TOLERANCE: f64 = 1e-3;

/// Whether the Gram route keeps every retained component's relative error
/// below [`GRAM_TOLERANCE`] whatever the spectrum: forming `A·Aᵀ` perturbs
/// its eigenvalues by about `ε·s_max²`, so the smallest one the truncation
/// may keep, `(truncation·s_max)²`, is off by `ε / truncation²` relatively
/// (`ε` of the precision used). For `f64` this admits truncations down to
/// about `4.7·10⁻⁷` (the published nonlinear-oscillator setting, 10⁻⁶, is
/// in; the linear one, 10⁻¹⁰, is not, and there [`Decomposition::Checked`]
/// looks at the spectrum actually kept).
pub fn gram_is_accurate(truncation: f64, single: bool) -> bool {
    truncation > 0.0 && epsilon(single) / (truncation * truncation) <= GRAM_TOLERANCE
}

/// The machine epsilon of `f32` (`single`) or `f64`.
fn epsilon(single: bool) -> f64 {
    if single { f64::from(f32::EPSILON) } else { f64::EPSILON }
}

/// [`pseudo_inverse_power_apply`] by a chosen decomposition and precision.
///
/// # Panics
/// If `a.len() != m·n` or `b.len() != m`.
pub fn pseudo_inverse_power_apply_with(m: usize, n: usize, a: &[f64], b: &[f64], beta: f64, truncation: f64, how: PowerMethod) -> Result<Vec<f64>, SvdFailed> {
    assert_eq!(a.len(), m * n, "pseudo-inverse: the matrix has the wrong length");
    assert_eq!(b.len(), m, "pseudo-inverse: the right-hand side has the wrong length");
    if how.single {
        let a32: Vec<f32> = a.iter().map(|&v| v as f32).collect();
        power_apply(faer::MatRef::from_row_major_slice(&a32, m, n), b, beta, truncation, how.decomposition)
    } else {
        power_apply(faer::MatRef::from_row_major_slice(a, m, n), b, beta, truncation, how.decomposition)
    }
}

/// The lower triangle of `B·Bᵀ` (what the eigensolver reads; the rest is
/// left zero), its row blocks in parallel (rayon; faer's own parallel
/// products would bring a scheduler and tracing crates in).
fn gram<T: Precision>(b: faer::MatRef<'_, T>) -> faer::Mat<T> {
    // Rows `first..first + dst.nrows()` of the product, up to the diagonal.
    fn rows<T: Precision>(dst: faer::MatMut<'_, T>, first: usize, b: faer::MatRef<'_, T>) {
        let h = dst.nrows();
        if h > 32 {
            let (top, bottom) = dst.split_at_row_mut(h / 2);
            rayon::join(|| rows(top, first, b), || rows(bottom, first + h / 2, b));
        } else {
            let end = first + h;
            let lhs = b.subrows(first, h);
            let rhs = b.subrows(0, end).transpose();
            faer::linalg::matmul::matmul(dst.subcols_mut(0, end), faer::Accum::Replace, lhs, rhs, T::one_impl(), faer::Par::Seq);
        }
    }
    let mut g = faer::Mat::<T>::zeros(b.nrows(), b.nrows());
    rows(g.as_mut(), 0, b);
    g
}

/// `f32` or `f64`, read as `f64`.
trait Precision: faer::traits::RealField + Copy + Into<f64> {}
impl Precision for f32 {}
impl Precision for f64 {}

fn power_apply<T: Precision>(a: faer::MatRef<'_, T>, b: &[f64], beta: f64, truncation: f64, how: Decomposition) -> Result<Vec<f64>, SvdFailed> {
    let (m, n) = (a.nrows(), a.ncols());
    // Aᵀ·y, row by row of the row-major A.
    let at_mul = |y: &[f64]| -> Vec<f64> {
        let mut x = vec![0.0; n];
        for (i, &yi) in y.iter().enumerate() {
            for (j, xj) in x.iter_mut().enumerate() {
                *xj += a[(i, j)].into() * yi;
            }
        }
        x
    };
    let svd = || -> Result<Vec<f64>, SvdFailed> {
        let d = a.thin_svd().map_err(|_| SvdFailed)?;
        let (u, v, s) = (d.U(), d.V(), d.S().column_vector());
        let s: Vec<f64> = (0..m.min(n)).map(|c| s[c].into()).collect();
        let cutoff = truncation * s.first().copied().unwrap_or(0.0);
        // c = diag(s^-β)·Uᵀ·b over the kept singular values, x = V·c.
        let c: Vec<f64> = (0..s.len())
            .map(|k| if s[k] > cutoff && s[k] > 0.0 { (0..m).map(|i| u[(i, k)].into() * b[i]).sum::<f64>() / s[k].powf(beta) } else { 0.0 })
            .collect();
        Ok((0..n).map(|j| c.iter().enumerate().map(|(k, ck)| v[(j, k)].into() * ck).sum()).collect())
    };
    // The Gram route; `None` when `checked` and a kept eigenvalue is too
    // near the rounding floor of the Gram matrix.
    let gram_route = |checked: bool| -> Result<Option<Vec<f64>>, SvdFailed> {
        // With W, λ = s² the eigenpairs of the smaller Gram matrix:
        // m ≤ n: A·Aᵀ = U·S²·Uᵀ, so V = Aᵀ·U·S⁻¹ and x = Aᵀ·U·S^(−1−β)·Uᵀ·b;
        // m > n: Aᵀ·A = V·S²·Vᵀ, Uᵀ·b = S⁻¹·Vᵀ·Aᵀ·b, x = V·S^(−1−β)·Vᵀ·(Aᵀ·b).
        let wide = m <= n;
        let g = gram(if wide { a } else { a.transpose() });
        let e = g.self_adjoint_eigen(faer::Side::Lower).map_err(|_| SvdFailed)?;
        let (w, lam) = (e.U(), e.S().column_vector());
        let k = g.nrows();
        let lam: Vec<f64> = (0..k).map(|c| lam[c].into()).collect();
        let lmax = lam.iter().copied().fold(0.0, f64::max);
        let cutoff = truncation * truncation * lmax;
        let kept = |l: f64| l > cutoff && l > 0.0;
        let eps = epsilon(std::mem::size_of::<T>() == 4);
        if checked && lam.iter().any(|&l| kept(l) && eps * lmax > GRAM_TOLERANCE * l) {
            return Ok(None);
        }
        let rhs: Vec<f64> = if wide { b.to_vec() } else { at_mul(b) };
        let mut y = vec![0.0; k];
        for c in 0..k {
            if kept(lam[c]) {
                let dot: f64 = (0..k).map(|i| w[(i, c)].into() * rhs[i]).sum();
                let scale = dot * lam[c].powf(-0.5 * (1.0 + beta));
                for (i, yi) in y.iter_mut().enumerate() {
                    *yi += w[(i, c)].into() * scale;
                }
            }
        }
        Ok(Some(if wide { at_mul(&y) } else { y }))
    };
    match how {
        Decomposition::Svd => svd(),
        Decomposition::Gram => Ok(gram_route(false)?.expect("an unchecked Gram route always answers")),
        Decomposition::Checked => match gram_route(true)? {
            Some(x) => Ok(x),
            None => svd(),
        },
    }
}

/// A sparse symmetric positive definite matrix factored once by faer's
/// sparse Cholesky (`L·Lᵀ`, fill-reducing ordering), then solved many
/// times: the pressure matrix of a fixed domain.
#[derive(Clone, Debug)]
pub struct SparseCholesky {
    llt: faer::sparse::linalg::solvers::Llt<usize, f64>,
    n: usize,
}

/// Why a sparse Cholesky factorisation failed (the matrix is not positive
/// definite, or memory ran out).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FactorFailed(pub String);

impl SparseCholesky {
    /// Factors the `n × n` matrix given by its lower-triangle entries
    /// `(row, column, value)`, `row ≥ column` (duplicates are summed).
    pub fn new(n: usize, lower: &[(usize, usize, f64)]) -> Result<Self, FactorFailed> {
        use faer::sparse::{SparseColMat, Triplet};
        let triplets: Vec<Triplet<usize, usize, f64>> = lower.iter().map(|&(r, c, v)| Triplet::new(r, c, v)).collect();
        let mat = SparseColMat::<usize, f64>::try_new_from_triplets(n, n, &triplets).map_err(|e| FactorFailed(format!("{e:?}")))?;
        let symbolic = faer::sparse::linalg::solvers::SymbolicLlt::try_new(mat.symbolic(), faer::Side::Lower).map_err(|e| FactorFailed(format!("{e:?}")))?;
        let llt =
            faer::sparse::linalg::solvers::Llt::try_new_with_symbolic(symbolic, mat.as_ref(), faer::Side::Lower).map_err(|e| FactorFailed(format!("{e:?}")))?;
        Ok(Self { llt, n })
    }

    /// Overwrites `b` with `A⁻¹·b`.
    pub fn solve_in_place(&self, b: &mut [f64]) {
        use faer::linalg::solvers::SolveCore;
        assert_eq!(b.len(), self.n, "sparse Cholesky: right-hand side length");
        let rhs = faer::MatMut::from_column_major_slice_mut(b, self.n, 1);
        self.llt.solve_in_place_with_conj(faer::Conj::No, rhs);
    }
}

/// The largest system [`dense_solve`] takes.
pub const DENSE_SOLVE_MAX: usize = 64;

/// Solves `A·x = b` (`transposed`: `Aᵀ·x = b`) in place of `b` for a small
/// dense `n × n` matrix `a` given column by column, which it overwrites with
/// its LU factors (faer's LU with partial pivoting): the Jacobians of
/// Newton's method on a few unknowns (an ODE's state), where setting up a
/// sparse factorisation would cost many times the arithmetic. The
/// permutations and faer's workspace live on the stack: no allocation. One
/// call factors and solves, so that no faer type reaches the crates built
/// with the autodiff flag (rustc's type trees crash on them). A singular
/// matrix leaves infinities or NaN in `b`.
///
/// # Panics
/// If `n` exceeds [`DENSE_SOLVE_MAX`], `a` does not hold `n²` values or `b`
/// not `n`.
pub fn dense_solve(n: usize, a: &mut [f64], b: &mut [f64], transposed: bool) {
    let (mut fwd, mut bwd) = ([0usize; DENSE_SOLVE_MAX], [0usize; DENSE_SOLVE_MAX]);
    dense_factor(n, a, &mut fwd[..n], &mut bwd[..n]);
    dense_factored_solve(n, a, &fwd[..n], &bwd[..n], b, transposed);
}

/// A small dense matrix's LU factors (faer's LU with partial pivoting),
/// kept to solve many right-hand sides: Newton's method with a Jacobian
/// held over several iterations. Plain vectors inside (no faer type, for
/// the crates built with the autodiff flag); each call to faer is one
/// non-generic function.
#[derive(Clone, Debug, Default)]
pub struct DenseLu {
    n: usize,
    lu: Vec<f64>,
    forward: Vec<usize>,
    inverse: Vec<usize>,
}

impl DenseLu {
    /// Factors the `n × n` matrix `a` (column by column) into this value's
    /// storage, reused from call to call; `false` when a factor is not
    /// finite (a singular matrix).
    ///
    /// # Panics
    /// If `n` exceeds [`DENSE_SOLVE_MAX`] or `a` does not hold `n²` values.
    pub fn factor(&mut self, n: usize, a: &[f64]) -> bool {
        self.n = n;
        self.lu.clear();
        self.lu.extend_from_slice(a);
        self.forward.resize(n, 0);
        self.inverse.resize(n, 0);
        dense_factor(n, &mut self.lu, &mut self.forward, &mut self.inverse);
        self.lu.iter().all(|v| v.is_finite()) && (0..n).all(|i| self.lu[i * n + i] != 0.0)
    }

    /// Unknowns of the factored matrix.
    pub fn n(&self) -> usize {
        self.n
    }

    /// `b = A⁻¹·b` (`transposed`: `A⁻ᵀ·b`).
    ///
    /// # Panics
    /// If `b` does not hold `n` values.
    pub fn solve(&self, b: &mut [f64], transposed: bool) {
        dense_factored_solve(self.n, &self.lu, &self.forward, &self.inverse, b, transposed);
    }
}

/// faer's workspace for a dense LU of at most [`DENSE_SOLVE_MAX`] unknowns
/// and its solves, on the stack.
type DenseStack = [std::mem::MaybeUninit<u8>; 8 * DENSE_SOLVE_MAX + 256];

fn dense_factor(n: usize, a: &mut [f64], forward: &mut [usize], inverse: &mut [usize]) {
    use faer::dyn_stack::{MemStack, StackReq};
    use faer::linalg::lu::partial_pivoting::factor;
    assert!(n <= DENSE_SOLVE_MAX, "dense LU: {n} unknowns, at most {DENSE_SOLVE_MAX}");
    assert_eq!(a.len(), n * n, "dense LU: the matrix must hold n² values");
    let par = faer::Par::Seq;
    let req = StackReq::any_of(&[factor::lu_in_place_scratch::<usize, f64>(n, n, par, Default::default())]);
    // n usizes or n doubles, aligned: 64 of either and their alignment fit.
    let mut buffer: DenseStack = [std::mem::MaybeUninit::uninit(); 8 * DENSE_SOLVE_MAX + 256];
    assert!(req.unaligned_bytes_required() <= buffer.len(), "dense LU: faer's workspace outgrew the stack buffer");
    let stack = MemStack::new(&mut buffer);
    let lu = faer::MatMut::from_column_major_slice_mut(a, n, n);
    factor::lu_in_place(lu, forward, inverse, par, stack, Default::default());
}

fn dense_factored_solve(n: usize, lu: &[f64], forward: &[usize], inverse: &[usize], b: &mut [f64], transposed: bool) {
    use faer::dyn_stack::{MemStack, StackReq};
    use faer::linalg::lu::partial_pivoting::solve;
    assert_eq!(b.len(), n, "dense LU: right-hand side length");
    let par = faer::Par::Seq;
    let req = StackReq::any_of(&[solve::solve_in_place_scratch::<usize, f64>(n, 1, par), solve::solve_transpose_in_place_scratch::<usize, f64>(n, 1, par)]);
    let mut buffer: DenseStack = [std::mem::MaybeUninit::uninit(); 8 * DENSE_SOLVE_MAX + 256];
    assert!(req.unaligned_bytes_required() <= buffer.len(), "dense LU: faer's workspace outgrew the stack buffer");
    let stack = MemStack::new(&mut buffer);
    let perm = faer::perm::PermRef::new_checked(forward, inverse, n);
    let lu = faer::MatRef::from_column_major_slice(lu, n, n);
    let rhs = faer::MatMut::from_column_major_slice_mut(b, n, 1);
    // L (unit lower) and U (upper) share the factored matrix: the
    // triangular solves read their own triangle only.
    if transposed {
        solve::solve_transpose_in_place_with_conj(lu, lu, perm, faer::Conj::No, rhs, par, stack);
    } else {
        solve::solve_in_place_with_conj(lu, lu, perm, faer::Conj::No, rhs, par, stack);
    }
}

/// A sparse square matrix factored by faer's sparse LU (partial pivoting,
/// fill-reducing column ordering), then solved with it or its transpose:
/// the Jacobians of Newton's method and their adjoints.
#[derive(Clone, Debug)]
pub struct SparseLu {
    lu: faer::sparse::linalg::solvers::Lu<usize, f64>,
    n: usize,
}

impl SparseLu {
    /// Factors the `n × n` matrix given by its entries `(row, column,
    /// value)` (duplicates are summed).
    pub fn new(n: usize, entries: &[(usize, usize, f64)]) -> Result<Self, FactorFailed> {
        use faer::sparse::{SparseColMat, Triplet};
        let triplets: Vec<Triplet<usize, usize, f64>> = entries.iter().map(|&(r, c, v)| Triplet::new(r, c, v)).collect();
        let mat = SparseColMat::<usize, f64>::try_new_from_triplets(n, n, &triplets).map_err(|e| FactorFailed(format!("{e:?}")))?;
        let lu = mat.sp_lu().map_err(|e| FactorFailed(format!("{e:?}")))?;
        Ok(Self { lu, n })
    }

    /// Overwrites `b` with `A⁻¹·b`.
    pub fn solve_in_place(&self, b: &mut [f64]) {
        use faer::linalg::solvers::SolveCore;
        assert_eq!(b.len(), self.n, "sparse LU: right-hand side length");
        let rhs = faer::MatMut::from_column_major_slice_mut(b, self.n, 1);
        self.lu.solve_in_place_with_conj(faer::Conj::No, rhs);
    }

    /// Overwrites `b` with `A⁻ᵀ·b` (the adjoint solve).
    pub fn solve_transpose_in_place(&self, b: &mut [f64]) {
        use faer::linalg::solvers::SolveCore;
        assert_eq!(b.len(), self.n, "sparse LU: right-hand side length");
        let rhs = faer::MatMut::from_column_major_slice_mut(b, self.n, 1);
        self.lu.solve_transpose_in_place_with_conj(faer::Conj::No, rhs);
    }
}

#[cfg(test)]
mod tests {
    use super::{DenseLu, dense_solve};

    /// A 3×3 system whose first pivot is 0 (so rows must swap), solved both
    /// ways and checked by multiplying back.
    #[test]
    fn dense_solve_pivots_and_solves_both_ways() {
        // Column by column: A = [[0, 2, 1], [1, 1, 0], [4, 0, 3]].
        let a = [0.0, 1.0, 4.0, 2.0, 1.0, 0.0, 1.0, 0.0, 3.0];
        let at = |i: usize, j: usize| a[j * 3 + i];
        let b = [3.0, -1.0, 2.5];
        for transposed in [false, true] {
            let (mut lu, mut x) = (a, b);
            dense_solve(3, &mut lu, &mut x, transposed);
            for (i, &bi) in b.iter().enumerate() {
                let row: f64 = (0..3).map(|j| if transposed { at(j, i) } else { at(i, j) } * x[j]).sum();
                assert!((row - bi).abs() < 1e-14, "transposed {transposed}, row {i}: {row} against {bi}");
            }
        }
        // Singular: infinities or NaN, not a number that looks right.
        let (mut lu, mut x) = ([1.0, 2.0, 2.0, 4.0], [1.0, 1.0]);
        dense_solve(2, &mut lu, &mut x, false);
        assert!(x.iter().any(|v| !v.is_finite()), "{x:?}");
    }

    /// Factors kept: the same answers as `dense_solve` for several
    /// right-hand sides both ways, and a singular matrix reported.
    #[test]
    fn dense_lu_keeps_its_factors_for_many_solves() {
        let a = [0.0, 1.0, 4.0, 2.0, 1.0, 0.0, 1.0, 0.0, 3.0];
        let mut lu = DenseLu::default();
        assert!(lu.factor(3, &a));
        assert_eq!(lu.n(), 3);
        for (k, transposed) in [(0, false), (1, true), (2, false)] {
            let b = [1.0 + k as f64, -2.0, 0.5 * k as f64];
            let (mut kept, mut once, mut fresh) = (b, b, a);
            lu.solve(&mut kept, transposed);
            dense_solve(3, &mut fresh, &mut once, transposed);
            assert_eq!(kept, once, "right-hand side {k}");
        }
        assert!(!lu.factor(2, &[1.0, 2.0, 2.0, 4.0]), "a singular matrix factored");
    }
}
