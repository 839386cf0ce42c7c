//! Grid passes split over threads (rayon) so that the result does not
//! depend on the thread count: every pass here writes disjoint pieces of its
//! output (slabs or rows), each computed by the same code whether it runs on
//! one thread or many, and sums are taken over fixed pieces added in a fixed
//! order. Small grids stay on the calling thread (the split would cost more
//! than it saves); since the pieces are the same either way, so is the
//! result.
//!
//! Nothing here may be called from a function Enzyme differentiates: the
//! generated adjoints run on one thread, and the parallel passes are the
//! forward steps and the linear solves outside them.

use rayon::prelude::*;

/// Values below which a pass runs on the calling thread.
pub const MIN_PARALLEL: usize = 1 << 12;

/// Calls `f(k, piece)` for every piece `k` of `out` cut into pieces of
/// `len` values (the last may be shorter), on several threads when `out`
/// is large.
#[inline]
pub fn for_pieces<F>(out: &mut [f64], len: usize, f: F)
where
    F: Fn(usize, &mut [f64]) + Sync + Send,
{
    let len = len.max(1);
    if out.len() >= MIN_PARALLEL && out.len() > len {
        out.par_chunks_mut(len).enumerate().for_each(|(k, piece)| f(k, piece));
    } else {
        out.chunks_mut(len).enumerate().for_each(|(k, piece)| f(k, piece));
    }
}

/// Calls `f(k, a_piece, b_piece)` for the matching pieces of two outputs
/// (`a` in pieces of `la` values, `b` of `lb`; as many pieces each).
#[inline]
pub fn for_pieces2<F>(a: &mut [f64], la: usize, b: &mut [f64], lb: usize, f: F)
where
    F: Fn(usize, &mut [f64], &mut [f64]) + Sync + Send,
{
    let (la, lb) = (la.max(1), lb.max(1));
    if a.len() + b.len() >= MIN_PARALLEL && a.len() > la {
        a.par_chunks_mut(la).zip(b.par_chunks_mut(lb)).enumerate().for_each(|(k, (x, y))| f(k, x, y));
    } else {
        a.chunks_mut(la).zip(b.chunks_mut(lb)).enumerate().for_each(|(k, (x, y))| f(k, x, y));
    }
}

/// Rows of `n` values per piece of a pass over a plane split by rows: at
/// least 2048 values a piece (whole rows), so that small planes stay in
/// few pieces. Passes without sums give the same values for any split.
#[inline]
pub fn rows_per_piece(n: usize) -> usize {
    2048usize.div_ceil(n.max(1)).max(1)
}

/// Values per piece of a sum: each piece's partial sum is computed alone,
/// then the partial sums are added in order.
pub const SUM_PIECE: usize = 4096;

/// `Σ_k f(piece k of a, piece k of b)` over pieces of [`SUM_PIECE`] values,
/// the same for any thread count.
#[inline]
pub fn sum_pieces<F>(a: &[f64], b: &[f64], f: F) -> f64
where
    F: Fn(&[f64], &[f64]) -> f64 + Sync + Send,
{
    if a.len() >= MIN_PARALLEL && a.len() > SUM_PIECE {
        let parts: Vec<f64> = a.par_chunks(SUM_PIECE).zip(b.par_chunks(SUM_PIECE)).map(|(x, y)| f(x, y)).collect();
        parts.iter().sum()
    } else {
        a.chunks(SUM_PIECE).zip(b.chunks(SUM_PIECE)).map(|(x, y)| f(x, y)).sum()
    }
}

/// `Σ_k f(k, piece k of a, piece k of b)` over mutable pieces of
/// [`SUM_PIECE`] values (`k` locates the pieces of other arrays), the same
/// for any thread count.
#[inline]
pub fn sum_pieces_mut<F>(a: &mut [f64], b: &mut [f64], f: F) -> f64
where
    F: Fn(usize, &mut [f64], &mut [f64]) -> f64 + Sync + Send,
{
    if a.len() >= MIN_PARALLEL && a.len() > SUM_PIECE {
        let parts: Vec<f64> = a.par_chunks_mut(SUM_PIECE).zip(b.par_chunks_mut(SUM_PIECE)).enumerate().map(|(k, (x, y))| f(k, x, y)).collect();
        parts.iter().sum()
    } else {
        a.chunks_mut(SUM_PIECE).zip(b.chunks_mut(SUM_PIECE)).enumerate().map(|(k, (x, y))| f(k, x, y)).sum()
    }
}
