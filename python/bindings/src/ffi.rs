//! diffsim's operators as XLA FFI custom calls: `jax.ffi.ffi_call`
//! reaches [`diffsim_forward`], [`diffsim_vjp`] and [`diffsim_jvp`] straight from compiled
//! JAX code, with XLA's buffers (no Python, no GIL, no copies in or out).
//! The operator is named by the scalar attribute `op_id`, its index in
//! [`REGISTRY`] (filled by `Operator.ffi_id()`).
//!
//! The structs mirror XLA's C API (`xla/ffi/api/c_api.h`, API version 0.3,
//! shipped with jaxlib: `jax.ffi.include_dir()`); only the fields read here
//! are named, the rest are opaque pointers of the right size.

use std::ffi::{CString, c_void};
use std::sync::{Arc, Mutex};

use super::PyOp;

/// Every operator handed to XLA, by id (never removed: compiled JAX code
/// may call an id for as long as the process lives).
pub(crate) static REGISTRY: Mutex<Vec<Arc<dyn PyOp>>> = Mutex::new(Vec::new());

#[repr(C)]
struct ExtensionBase {
    struct_size: usize,
    kind: i32,
    next: *mut ExtensionBase,
}

#[repr(C)]
struct ApiVersion {
    struct_size: usize,
    extension_start: *mut ExtensionBase,
    major: i32,
    minor: i32,
}

#[repr(C)]
struct ErrorCreateArgs {
    struct_size: usize,
    extension_start: *mut ExtensionBase,
    message: *const std::ffi::c_char,
    code: i32,
}

#[repr(C)]
struct Api {
    struct_size: usize,
    extension_start: *mut ExtensionBase,
    version: ApiVersion,
    internal: *const c_void,
    error_create: Option<unsafe extern "C" fn(*mut ErrorCreateArgs) -> *mut c_void>,
}

#[repr(C)]
struct Buffer {
    struct_size: usize,
    extension_start: *mut ExtensionBase,
    dtype: i32,
    data: *mut c_void,
    rank: i64,
    dims: *const i64,
}

#[repr(C)]
struct List {
    struct_size: usize,
    extension_start: *mut ExtensionBase,
    size: i64,
    types: *const i32,
    items: *const *mut c_void,
}

#[repr(C)]
struct ByteSpan {
    ptr: *const u8,
    len: usize,
}

#[repr(C)]
struct Attrs {
    struct_size: usize,
    extension_start: *mut ExtensionBase,
    size: i64,
    types: *const i32,
    names: *const *const ByteSpan,
    attrs: *const *mut c_void,
}

#[repr(C)]
struct Scalar {
    dtype: i32,
    value: *const c_void,
}

#[repr(C)]
struct CallFrame {
    struct_size: usize,
    extension_start: *mut ExtensionBase,
    api: *const Api,
    ctx: *mut c_void,
    stage: i32,
    args: List,
    rets: List,
    attrs: Attrs,
    future: *mut c_void,
}

#[repr(C)]
struct Metadata {
    struct_size: usize,
    version: ApiVersion,
    traits: u32,
}

#[repr(C)]
struct MetadataExtension {
    base: ExtensionBase,
    metadata: *mut Metadata,
}

const EXTENSION_METADATA: i32 = 1;
const STAGE_EXECUTE: i32 = 3;
const F64: i32 = 12;
const S64: i32 = 5;
const ATTR_SCALAR: i32 = 3;
const INVALID_ARGUMENT: i32 = 3;
const INTERNAL: i32 = 13;

/// An XLA error carrying `message` (XLA copies it).
unsafe fn error(frame: &CallFrame, code: i32, message: &str) -> *mut c_void {
    let text = CString::new(message.replace('\0', " ")).unwrap_or_default();
    let mut args = ErrorCreateArgs { struct_size: std::mem::size_of::<ErrorCreateArgs>(), extension_start: std::ptr::null_mut(), message: text.as_ptr(), code };
    match unsafe { frame.api.as_ref().and_then(|a| a.error_create) } {
        Some(create) => unsafe { create(&mut args) },
        // No way to say it: a null error would claim success, so abort.
        None => std::process::abort(),
    }
}

/// Buffer `k` of `list`, float64: its data pointer, length and dims.
unsafe fn raw(list: &List, k: usize, what: &str) -> Result<(*mut f64, usize, Vec<usize>), String> {
    if (list.size as usize) <= k {
        return Err(format!("missing buffer {what}"));
    }
    let b = unsafe { &*(*list.items.add(k) as *const Buffer) };
    if b.dtype != F64 {
        return Err(format!("{what} must be float64"));
    }
    let dims: Vec<usize> = (0..b.rank as usize).map(|i| unsafe { *b.dims.add(i) } as usize).collect();
    let len = dims.iter().product();
    // An empty buffer may have a null pointer; a slice may not.
    let data = if len == 0 { std::ptr::NonNull::<f64>::dangling().as_ptr() } else { b.data as *mut f64 };
    Ok((data, len, dims))
}

/// An argument buffer.
unsafe fn input<'a>(f: &CallFrame, k: usize, what: &str) -> Result<(&'a [f64], Vec<usize>), String> {
    let (data, len, dims) = unsafe { raw(&f.args, k, what)? };
    Ok((unsafe { std::slice::from_raw_parts(data, len) }, dims))
}

/// A result buffer.
unsafe fn output<'a>(f: &CallFrame, k: usize, what: &str) -> Result<&'a mut [f64], String> {
    let (data, len, _) = unsafe { raw(&f.rets, k, what)? };
    Ok(unsafe { std::slice::from_raw_parts_mut(data, len) })
}

/// The registered operator the attribute `op_id` names.
unsafe fn operator(frame: &CallFrame) -> Result<Arc<dyn PyOp>, String> {
    let a = &frame.attrs;
    for i in 0..a.size as usize {
        let name = unsafe { &**a.names.add(i) };
        let name = unsafe { std::slice::from_raw_parts(name.ptr, name.len) };
        if name == b"op_id" && unsafe { *a.types.add(i) } == ATTR_SCALAR {
            let s = unsafe { &*(*a.attrs.add(i) as *const Scalar) };
            if s.dtype != S64 {
                return Err("op_id must be an int64".into());
            }
            let id = unsafe { *(s.value as *const i64) };
            let registry = REGISTRY.lock().unwrap_or_else(|e| e.into_inner());
            return registry.get(id as usize).cloned().ok_or_else(|| format!("no diffsim operator {id}"));
        }
    }
    Err("the call names no operator (attribute op_id)".into())
}

/// The frame checks every handler makes: the version query, the stage.
/// `Some(result)` when the handler is done.
unsafe fn preamble(frame: *mut CallFrame) -> Option<*mut c_void> {
    let f = unsafe { &*frame };
    if !f.extension_start.is_null() && unsafe { (*f.extension_start).kind } == EXTENSION_METADATA {
        let ext = unsafe { &mut *(f.extension_start as *mut MetadataExtension) };
        let m = unsafe { &mut *ext.metadata };
        m.version = ApiVersion { struct_size: std::mem::size_of::<ApiVersion>(), extension_start: std::ptr::null_mut(), major: 0, minor: 3 };
        m.traits = 0;
        return Some(std::ptr::null_mut());
    }
    if f.stage != STAGE_EXECUTE {
        return Some(std::ptr::null_mut());
    }
    None
}

/// Runs `body`, turning its error or panic into an XLA error.
unsafe fn run(frame: *mut CallFrame, body: impl FnOnce(&CallFrame) -> Result<(), String>) -> *mut c_void {
    if let Some(done) = unsafe { preamble(frame) } {
        return done;
    }
    let f = unsafe { &*frame };
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| body(f))) {
        Ok(Ok(())) => std::ptr::null_mut(),
        Ok(Err(m)) => unsafe { error(f, INVALID_ARGUMENT, &format!("diffsim: {m}")) },
        Err(p) => unsafe { error(f, INTERNAL, &format!("diffsim panicked: {}", super::panic_message(p))) },
    }
}

/// A non-finite input is an error, never passed on.
fn finite(v: &[f64], what: &str) -> Result<(), String> {
    match v.iter().position(|a| !a.is_finite()) {
        Some(i) => Err(format!("{what} holds a non-finite value ({}) at flat index {i}", v[i])),
        None => Ok(()),
    }
}

/// How many consecutive elements of `x` share one block of `p`: all of
/// them for a shared `p` (`[n_params]`), one for `p` batched like `x`, and
/// in between for `p` batched over the leading axes only (`vmap` of a
/// function called with a batch of its own).
fn p_block(len: usize, dims: &[usize], n_params: usize, count: usize) -> Result<usize, String> {
    let blocks = if dims.len() <= 1 { 1 } else { len / n_params.max(1) };
    if n_params == 0 {
        return Ok(count.max(1));
    }
    if len != blocks * n_params || blocks == 0 || !count.is_multiple_of(blocks) {
        return Err(format!("p ({len} values) does not fit {count} elements of {n_params} parameters"));
    }
    Ok((count / blocks).max(1))
}

/// What both handlers read first: the operator, `x` and `p` (arguments 0
/// and 1, checked), the number of elements and how many share a block of
/// `p`.
struct Inputs<'a> {
    op: Arc<dyn PyOp>,
    x: &'a [f64],
    p: &'a [f64],
    count: usize,
    per: usize,
}

unsafe fn inputs<'a>(f: &CallFrame) -> Result<Inputs<'a>, String> {
    let op = unsafe { operator(f)? };
    let (n_in, _, n_params) = op.sizes();
    let (x, _) = unsafe { input(f, 0, "x")? };
    let (p, pdims) = unsafe { input(f, 1, "p")? };
    let count = x.len() / n_in.max(1);
    if x.len() != count * n_in {
        return Err("x does not fit the operator".into());
    }
    let per = p_block(p.len(), &pdims, n_params, count)?;
    finite(x, "x")?;
    finite(p, "p")?;
    Ok(Inputs { op, x, p, count, per })
}

/// `y = f(x, p)`: args `x [..., n_in]`, `p [..., n_params]` (broadcast to
/// `x`'s batch) or `[n_params]`; result `y [..., n_out]`.
///
/// # Safety
/// Called by XLA with a valid call frame.
unsafe extern "C" fn diffsim_forward(frame: *mut CallFrame) -> *mut c_void {
    unsafe {
        run(frame, |f| {
            let Inputs { op, x, p, count, per } = inputs(f)?;
            let n_out = op.sizes().1;
            let y = output(f, 0, "y")?;
            if y.len() != count * n_out {
                return Err("buffer sizes do not fit the operator".into());
            }
            super::forward_rows(&*op, x, p, per, y).map_err(super::message)?;
            Ok(())
        })
    }
}

/// `(dx, dp) = (J_xᵀ·dy, J_pᵀ·dy)`: args `x`, `p`, `dy`; results `dx`
/// (`x`'s shape) and `dp [..., n_params]` per element.
///
/// # Safety
/// Called by XLA with a valid call frame.
unsafe extern "C" fn diffsim_vjp(frame: *mut CallFrame) -> *mut c_void {
    unsafe {
        run(frame, |f| {
            let Inputs { op, x, p, count, per } = inputs(f)?;
            let (_, n_out, n_params) = op.sizes();
            let (dy, _) = input(f, 2, "dy")?;
            let dx = output(f, 0, "dx")?;
            let dp = output(f, 1, "dp")?;
            finite(dy, "dy")?;
            if dy.len() != count * n_out || dx.len() != x.len() || dp.len() != count * n_params {
                return Err("buffer sizes do not fit the operator".into());
            }
            super::vjp_rows(&*op, x, p, per, dy, dx, dp).map_err(super::message)?;
            Ok(())
        })
    }
}

/// `ty = J_x·tx + J_p·tp` (the JVP, linear in the tangents): args `x`, `p`,
/// `tx` (`x`'s shape), `tp` (`p`'s shape); result `ty [..., n_out]`. The
/// value `y` is computed on the way and dropped: `diffsim.jax` asks for it
/// through [`diffsim_forward`], so that JAX can transpose this call alone.
///
/// # Safety
/// Called by XLA with a valid call frame.
unsafe extern "C" fn diffsim_jvp(frame: *mut CallFrame) -> *mut c_void {
    unsafe {
        run(frame, |f| {
            let Inputs { op, x, p, count, per } = inputs(f)?;
            let n_out = op.sizes().1;
            let (tx, _) = input(f, 2, "tx")?;
            let (tp, _) = input(f, 3, "tp")?;
            let ty = output(f, 0, "ty")?;
            finite(tx, "tx")?;
            finite(tp, "tp")?;
            if tx.len() != x.len() || tp.len() != p.len() || ty.len() != count * n_out {
                return Err("buffer sizes do not fit the operator".into());
            }
            let mut y = vec![0.0; ty.len()];
            super::jvp_rows(&*op, x, p, per, tx, tp, &mut y, ty).map_err(super::message)?;
            Ok(())
        })
    }
}

/// The targets to register with `jax.ffi.register_ffi_target`: names and
/// function addresses.
pub(crate) fn targets() -> Vec<(&'static str, usize)> {
    vec![
        ("diffsim_forward", diffsim_forward as *const () as usize),
        ("diffsim_vjp", diffsim_vjp as *const () as usize),
        ("diffsim_jvp", diffsim_jvp as *const () as usize),
    ]
}
