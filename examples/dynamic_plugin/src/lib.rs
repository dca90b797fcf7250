//! `example.invert`: inverts an image (`255 - v`), as a plugin loaded at run time.
//!
//! Build: `cargo build --release --manifest-path examples/dynamic_plugin/Cargo.toml`, then name
//! the library in a graph: `[graph] libraries = ["examples/dynamic_plugin/target/release/libmisslam_example_invert.so"]`.
//! Parameters arrive as a TOML table in text; this example parses its two by hand to stay
//! dependency-free (a real plugin would use the `toml` crate).

use std::ffi::c_void;

use misslam_abi::{
    self as abi, Buffer, BufferDesc, BufferKind, ErrorBuf, OutputSink, PluginVTable, PortDesc, Str,
};

struct Invert {
    /// Added to every inverted value (saturating).
    offset: u8,
    /// Panic on this frame, to show that a plugin panic is reported, not fatal (-1: never).
    panic_on_frame: i64,
}

fn parse_params(text: &str) -> Result<Invert, String> {
    let mut p = Invert {
        offset: 0,
        panic_on_frame: -1,
    };
    for line in text.lines().map(str::trim).filter(|l| !l.is_empty()) {
        let (k, v) = line
            .split_once('=')
            .ok_or_else(|| format!("cannot read `{line}`"))?;
        let (k, v) = (k.trim(), v.trim());
        match k {
            "offset" => {
                p.offset = v
                    .parse()
                    .map_err(|_| format!("parameter `offset`: `{v}` is not an integer 0..=255"))?
            }
            "panic_on_frame" => {
                p.panic_on_frame = v
                    .parse()
                    .map_err(|_| format!("parameter `panic_on_frame`: `{v}` is not an integer"))?
            }
            other => {
                return Err(format!(
                    "unknown parameter `{other}`; known: offset, panic_on_frame"
                ))
            }
        }
    }
    Ok(p)
}

unsafe extern "C" fn create(params: Str, err: *mut ErrorBuf) -> *mut c_void {
    let mut state: *mut c_void = std::ptr::null_mut();
    // SAFETY: err comes from the host.
    unsafe {
        abi::guard(err, || {
            // SAFETY (of the enclosing block): the host passes a valid string for the call.
            let text = params.as_str().map_err(|e| e.to_string())?;
            state = Box::into_raw(Box::new(parse_params(text)?)) as *mut c_void;
            Ok(())
        })
    };
    state
}

unsafe extern "C" fn process(
    state: *mut c_void,
    frame: u64,
    inputs: *const Buffer,
    n_inputs: usize,
    sink: *const OutputSink,
    err: *mut ErrorBuf,
) -> i32 {
    // SAFETY: err comes from the host.
    unsafe {
        abi::guard(err, || {
            // SAFETY: state was made by `create`; inputs/sink are valid during the call.
            let me = &*(state as *const Invert);
            if me.panic_on_frame >= 0 && frame == me.panic_on_frame as u64 {
                panic!("example.invert was asked to panic on frame {frame}");
            }
            if n_inputs != 1 {
                return Err(format!("expected 1 input, got {n_inputs}"));
            }
            let input = &*inputs;
            let desc = input.desc;
            let src = std::slice::from_raw_parts(input.data, desc.byte_len());
            let out_desc = BufferDesc { ..desc };
            let sink = &*sink;
            let dst = (sink.alloc)(sink.ctx, 0, &out_desc);
            if dst.is_null() {
                return Err("the host refused the output buffer".into());
            }
            let dst = std::slice::from_raw_parts_mut(dst, out_desc.byte_len());
            for (d, s) in dst.iter_mut().zip(src) {
                *d = (255 - *s).saturating_add(me.offset);
            }
            Ok(())
        })
    }
}

unsafe extern "C" fn destroy(state: *mut c_void) {
    if !state.is_null() {
        // SAFETY: state was made by `create` and is destroyed once; a panic in drop is caught.
        let _ = std::panic::catch_unwind(|| drop(unsafe { Box::from_raw(state as *mut Invert) }));
    }
}

static INPUTS: [PortDesc; 1] = [PortDesc {
    name: Str::from_static("image"),
    kind: BufferKind::Image as u32,
}];
static OUTPUTS: [PortDesc; 1] = [PortDesc {
    name: Str::from_static("inverted"),
    kind: BufferKind::Image as u32,
}];

static VTABLE: PluginVTable = PluginVTable {
    abi_version: if cfg!(feature = "wrong-abi") { 999 } else { abi::ABI_VERSION },
    abi_crate_version: Str::from_static(abi::ABI_CRATE_VERSION),
    rustc_version: Str::from_static(abi::RUSTC_VERSION),
    id: Str::from_static("example.invert"),
    summary: Str::from_static("inverts an image (a plugin loaded at run time)"),
    params_doc: Str::from_static(
        "offset: integer 0..=255 = 0; added to every inverted value\npanic_on_frame: integer = -1; panic on this frame (tests)",
    ),
    inputs: INPUTS.as_ptr(),
    n_inputs: 1,
    outputs: OUTPUTS.as_ptr(),
    n_outputs: 1,
    create,
    process,
    destroy,
};

/// The entry point misslam looks up.
#[no_mangle]
pub extern "C" fn misslam_plugin_entry_v1() -> *const PluginVTable {
    &VTABLE
}
