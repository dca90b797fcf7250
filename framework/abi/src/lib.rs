//! The C ABI between misslam and plugin libraries loaded at run time.
//!
//! Only `repr(C)` data and raw buffers cross this boundary, so a plugin may be built by another
//! rustc (or in another language) than the host. A plugin library exports one symbol,
//! [`ENTRY_SYMBOL`], an `extern "C" fn() -> *const PluginVTable`. The host checks the handshake
//! fields ([`PluginVTable::abi_version`], [`PluginVTable::abi_crate_version`],
//! [`PluginVTable::rustc_version`]) before it calls anything else. Every function a plugin exports
//! must catch panics ([`guard`] does this) and report failure through an [`ErrorBuf`].
//!
//! Memory: input buffers are owned by the host and valid during one `process` call. Outputs are
//! allocated by the host through [`OutputSink::alloc`] and filled by the plugin, so no allocation
//! ever crosses the boundary. The host never unloads a plugin library.
#![deny(missing_docs)]

use std::ffi::c_void;
use std::panic::{catch_unwind, AssertUnwindSafe};

/// Version of this ABI. The host refuses a library whose `abi_version` differs.
pub const ABI_VERSION: u32 = 1;

/// Name of the entry point a plugin library exports (NUL-terminated for dlsym).
pub const ENTRY_SYMBOL: &[u8] = b"misslam_plugin_entry_v1\0";

/// Version of this crate, which the host compares (major.minor) with the plugin's.
pub const ABI_CRATE_VERSION: &str = env!("CARGO_PKG_VERSION");

/// The rustc that compiled this crate (informational: only C types cross the boundary).
pub const RUSTC_VERSION: &str = env!("MISSLAM_ABI_RUSTC_VERSION");

/// Return code of a successful call.
pub const OK: i32 = 0;
/// Return code of a call that failed with a message in its [`ErrorBuf`].
pub const ERR: i32 = 1;
/// Return code of a call that panicked (the message is in its [`ErrorBuf`]).
pub const PANICKED: i32 = 2;

/// A borrowed UTF-8 string: pointer and length, no terminator.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct Str {
    /// First byte.
    pub ptr: *const u8,
    /// Length in bytes.
    pub len: usize,
}

impl Str {
    /// Borrows a `'static` string.
    pub const fn from_static(s: &'static str) -> Self {
        Str {
            ptr: s.as_ptr(),
            len: s.len(),
        }
    }

    /// Borrows any string for the duration of a call.
    pub fn borrow(s: &str) -> Self {
        Str {
            ptr: s.as_ptr(),
            len: s.len(),
        }
    }

    /// Reads the string back.
    ///
    /// # Safety
    /// `ptr` must point to `len` readable bytes that outlive `'a`.
    pub unsafe fn as_str<'a>(&self) -> Result<&'a str, std::str::Utf8Error> {
        if self.len == 0 {
            return Ok("");
        }
        // SAFETY: the caller guarantees ptr/len describe live bytes.
        let bytes = unsafe { std::slice::from_raw_parts(self.ptr, self.len) };
        std::str::from_utf8(bytes)
    }
}

// SAFETY: a `Str` in a vtable or port table points to immutable static bytes.
unsafe impl Sync for Str {}
// SAFETY: as above; the pointer is only read.
unsafe impl Send for Str {}

/// What a port carries across the boundary.
#[repr(u32)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BufferKind {
    /// Interleaved 8-bit image, 1 or 3 channels (`image` port type).
    Image = 1,
    /// Disparity map, `f32` per pixel in pixels, NaN where invalid (`disparity` port type).
    Disparity = 2,
    /// Depth map, `f32` per pixel in mm, NaN where invalid (`depth` port type).
    Depth = 3,
}

impl BufferKind {
    /// Decodes a raw kind, if it is known.
    pub fn from_raw(raw: u32) -> Option<Self> {
        match raw {
            1 => Some(BufferKind::Image),
            2 => Some(BufferKind::Disparity),
            3 => Some(BufferKind::Depth),
            _ => None,
        }
    }
}

/// Declaration of one input or output port.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct PortDesc {
    /// Port name, unique among the plugin's inputs (or outputs).
    pub name: Str,
    /// A [`BufferKind`] as `u32`.
    pub kind: u32,
}

/// Rectified stereo calibration carried with disparity and depth maps.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Calib {
    /// Focal length x, pixels.
    pub fx: f64,
    /// Focal length y, pixels.
    pub fy: f64,
    /// Principal point x of the left camera, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Principal point x of the right camera, pixels.
    pub cx_right: f64,
    /// Baseline, mm.
    pub baseline_mm: f64,
}

/// Shape of a buffer.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct BufferDesc {
    /// A [`BufferKind`] as `u32`.
    pub kind: u32,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Channels: 1 or 3 for images, 1 for maps.
    pub channels: u32,
    /// 1 when `calib` is meaningful.
    pub has_calib: u32,
    /// Calibration of a disparity or depth map.
    pub calib: Calib,
}

impl BufferDesc {
    /// Size in bytes of a buffer of this shape.
    pub fn byte_len(&self) -> usize {
        let elem = match BufferKind::from_raw(self.kind) {
            Some(BufferKind::Image) => 1,
            _ => 4,
        };
        self.width as usize * self.height as usize * self.channels as usize * elem
    }
}

/// A borrowed input buffer: u8 for images, native-endian f32 for maps, rows tightly packed.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct Buffer {
    /// Shape.
    pub desc: BufferDesc,
    /// First byte; `desc.byte_len()` bytes are readable.
    pub data: *const u8,
}

/// Host callback table through which a plugin allocates its outputs.
#[repr(C)]
pub struct OutputSink {
    /// Opaque host state.
    pub ctx: *mut c_void,
    /// Allocates output `port` (index into the plugin's outputs) with shape `desc`; returns a
    /// writable, zeroed buffer of `desc.byte_len()` bytes owned by the host, or null when the port
    /// or the shape is wrong. Allocating the same port twice replaces the first buffer.
    pub alloc:
        unsafe extern "C" fn(ctx: *mut c_void, port: u32, desc: *const BufferDesc) -> *mut u8,
}

/// Buffer for an error message written by the plugin (UTF-8, truncated to `cap`).
#[repr(C)]
pub struct ErrorBuf {
    /// Writable bytes.
    pub ptr: *mut u8,
    /// Capacity in bytes.
    pub cap: usize,
    /// Bytes written.
    pub len: usize,
}

impl ErrorBuf {
    /// Writes `msg`, truncated at a character boundary to the capacity.
    ///
    /// # Safety
    /// `ptr` must be valid for `cap` writable bytes.
    pub unsafe fn write(&mut self, msg: &str) {
        let mut n = msg.len().min(self.cap);
        while n > 0 && !msg.is_char_boundary(n) {
            n -= 1;
        }
        if n > 0 {
            // SAFETY: the caller guarantees ptr is valid for cap >= n bytes.
            unsafe { std::ptr::copy_nonoverlapping(msg.as_ptr(), self.ptr, n) };
        }
        self.len = n;
    }
}

/// Creates a plugin instance from its parameters, given as a TOML table in text.
/// Returns null on failure, with the reason in `err`.
pub type CreateFn = unsafe extern "C" fn(params_toml: Str, err: *mut ErrorBuf) -> *mut c_void;

/// Processes one frame: reads `inputs` (one per declared input, in order), allocates and fills
/// every declared output through `sink`. Returns [`OK`], [`ERR`] or [`PANICKED`].
pub type ProcessFn = unsafe extern "C" fn(
    state: *mut c_void,
    frame: u64,
    inputs: *const Buffer,
    n_inputs: usize,
    sink: *const OutputSink,
    err: *mut ErrorBuf,
) -> i32;

/// Destroys a plugin instance.
pub type DestroyFn = unsafe extern "C" fn(state: *mut c_void);

/// Everything the host needs from a plugin library. Returned by the entry point; must live as long
/// as the library (a `static`).
#[repr(C)]
pub struct PluginVTable {
    /// Must equal the host's [`ABI_VERSION`].
    pub abi_version: u32,
    /// [`ABI_CRATE_VERSION`] as the plugin saw it.
    pub abi_crate_version: Str,
    /// [`RUSTC_VERSION`] as the plugin saw it.
    pub rustc_version: Str,
    /// Plugin id used in graphs, e.g. `example.invert`.
    pub id: Str,
    /// One-line description.
    pub summary: Str,
    /// Parameter documentation shown by `misslam plugins ID`, one `name: type = default; doc` per line.
    pub params_doc: Str,
    /// Input ports.
    pub inputs: *const PortDesc,
    /// Number of input ports.
    pub n_inputs: usize,
    /// Output ports.
    pub outputs: *const PortDesc,
    /// Number of output ports.
    pub n_outputs: usize,
    /// Instance constructor.
    pub create: CreateFn,
    /// Per-frame call.
    pub process: ProcessFn,
    /// Instance destructor.
    pub destroy: DestroyFn,
}

// SAFETY: the vtable is immutable static data (pointers to static strings and functions).
unsafe impl Sync for PluginVTable {}

/// Signature of the entry point.
pub type EntryFn = unsafe extern "C" fn() -> *const PluginVTable;

/// Runs `f`, catching panics, and turns its outcome into a return code, writing any message to
/// `err`. Every function a plugin exports should be a call to this.
///
/// # Safety
/// `err` must be null or point to a valid [`ErrorBuf`].
pub unsafe fn guard(err: *mut ErrorBuf, f: impl FnOnce() -> Result<(), String>) -> i32 {
    let outcome = catch_unwind(AssertUnwindSafe(f));
    let (code, msg) = match outcome {
        Ok(Ok(())) => return OK,
        Ok(Err(msg)) => (ERR, msg),
        Err(payload) => (PANICKED, panic_message(payload.as_ref())),
    };
    if !err.is_null() {
        // SAFETY: the caller guarantees err is valid when non-null.
        unsafe { (*err).write(&msg) };
    }
    code
}

/// The text of a panic payload.
pub fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_owned()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "panic with a non-string payload".to_owned()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn guard_reports_errors_and_panics() {
        let mut bytes = [0u8; 16];
        let mut err = ErrorBuf {
            ptr: bytes.as_mut_ptr(),
            cap: bytes.len(),
            len: 0,
        };
        // SAFETY: err points to a live buffer.
        let ok = unsafe { guard(&mut err, || Ok(())) };
        assert_eq!(ok, OK);
        let code = unsafe { guard(&mut err, || Err("bad parameter `gain`".into())) };
        assert_eq!(code, ERR);
        assert_eq!(
            &bytes[..err.len],
            b"bad parameter `g",
            "truncated to capacity"
        );
        let code = unsafe { guard(&mut err, || panic!("boom")) };
        assert_eq!(code, PANICKED);
        assert_eq!(&bytes[..err.len], b"boom");
    }

    #[test]
    fn byte_len_depends_on_kind() {
        let mut d = BufferDesc {
            kind: BufferKind::Image as u32,
            width: 4,
            height: 2,
            channels: 3,
            has_calib: 0,
            calib: Calib::default(),
        };
        assert_eq!(d.byte_len(), 24);
        d.kind = BufferKind::Depth as u32;
        d.channels = 1;
        assert_eq!(d.byte_len(), 32);
    }
}
