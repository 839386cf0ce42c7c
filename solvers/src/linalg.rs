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
    let mat = faer::Mat::<f64>::from_fn(m, n, |i, j| a[i * n + j]);
    let d = mat.thin_svd().map_err(|_| SvdFailed)?;
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
/// gradients for `beta = ½`. `b` has `m` values, the result `n`.
pub fn pseudo_inverse_power_apply(m: usize, n: usize, a: &[f64], b: &[f64], beta: f64, truncation: f64) -> Result<Vec<f64>, SvdFailed> {
    let d = svd(m, n, a)?;
    let k = d.s.len();
    let cutoff = truncation * d.s.first().copied().unwrap_or(0.0);
    // c = diag(s^-β)·Uᵀ·b over the kept singular values.
    let mut c = vec![0.0; k];
    for (col, cv) in c.iter_mut().enumerate() {
        let s = d.s[col];
        if s > cutoff && s > 0.0 {
            let dot: f64 = (0..m).map(|i| d.u[i * k + col] * b[i]).sum();
            *cv = dot / s.powf(beta);
        }
    }
    Ok((0..n).map(|j| (0..k).map(|col| d.v[j * k + col] * c[col]).sum()).collect())
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
