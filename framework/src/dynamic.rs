//! Plugins loaded at run time from a shared library through the C ABI of `misslam-abi`.
//!
//! The handshake refuses a library built against another ABI version or another minor version of
//! `misslam-abi`; a different rustc is only logged, since nothing but `repr(C)` data crosses.
//! Loaded libraries are never unloaded (their code may still be referenced by nodes).

use std::ffi::c_void;
use std::path::Path;
use std::sync::{Arc, Mutex};

use misslam_abi as abi;

use crate::node::{
    Flow, FrameInfo, Inputs, Node, NodeContext, NodeError, NodeResult, Outputs, PortSpec,
};
use crate::payload::{DepthMap, DisparityMap, FloatMap, Image, Payload, PortType, StereoCalib};
use crate::registry::{BuildContext, BuildError, ParamDoc, Plugin, PluginInfo};

/// Libraries stay loaded for the life of the process.
static LOADED: Mutex<Vec<&'static libloading::Library>> = Mutex::new(Vec::new());

/// Loads a plugin library and checks its handshake.
pub fn load_library(path: &Path) -> Result<Arc<dyn Plugin>, String> {
    if !path.exists() {
        return Err(format!(
            "`{}` does not exist (build the plugin crate first, e.g. `cargo build --manifest-path examples/dynamic_plugin/Cargo.toml`)",
            path.display()
        ));
    }
    // SAFETY: loading a library runs its initialisers; the user named it in the graph.
    let lib = unsafe { libloading::Library::new(path) }
        .map_err(|e| format!("cannot load `{}`: {e}", path.display()))?;
    let lib: &'static libloading::Library = Box::leak(Box::new(lib));
    if let Ok(mut v) = LOADED.lock() {
        v.push(lib);
    }
    // SAFETY: the symbol's type is fixed by the ABI.
    let entry: libloading::Symbol<abi::EntryFn> =
        unsafe { lib.get(abi::ENTRY_SYMBOL) }.map_err(|e| {
            format!(
                "`{}` is not a misslam plugin: no entry point `{}` ({e})",
                path.display(),
                String::from_utf8_lossy(&abi::ENTRY_SYMBOL[..abi::ENTRY_SYMBOL.len() - 1])
            )
        })?;
    // SAFETY: the entry point takes nothing and returns a pointer to static data or null.
    let vt = unsafe { entry() };
    if vt.is_null() {
        return Err(format!(
            "`{}`: the entry point returned null",
            path.display()
        ));
    }
    // SAFETY: non-null pointer to a static vtable (ABI contract).
    let vt: &'static abi::PluginVTable = unsafe { &*vt };
    plugin_from_vtable(vt, &path.display().to_string())
}

fn read_str(s: abi::Str, what: &str) -> Result<String, String> {
    // SAFETY: the ABI requires strings in the vtable to be static.
    unsafe { s.as_str() }
        .map(str::to_owned)
        .map_err(|e| format!("{what} is not UTF-8: {e}"))
}

fn ports(ptr: *const abi::PortDesc, n: usize, what: &str) -> Result<Vec<PortSpec>, String> {
    if n == 0 {
        return Ok(Vec::new());
    }
    if ptr.is_null() {
        return Err(format!("{what}: null port table"));
    }
    // SAFETY: the vtable promises `n` static port descriptors.
    let descs = unsafe { std::slice::from_raw_parts(ptr, n) };
    descs
        .iter()
        .map(|d| {
            let name = read_str(d.name, "port name")?;
            let ty = match abi::BufferKind::from_raw(d.kind) {
                Some(abi::BufferKind::Image) => PortType::Image,
                Some(abi::BufferKind::Disparity) => PortType::Disparity,
                Some(abi::BufferKind::Depth) => PortType::Depth,
                None => return Err(format!("{what} `{name}`: unknown buffer kind {}", d.kind)),
            };
            Ok(PortSpec::new(&name, ty, ""))
        })
        .collect()
}

/// Checks the handshake and wraps a vtable as a plugin (`origin` names the library).
pub fn plugin_from_vtable(
    vt: &'static abi::PluginVTable,
    origin: &str,
) -> Result<Arc<dyn Plugin>, String> {
    if vt.abi_version != abi::ABI_VERSION {
        return Err(format!(
            "`{origin}` speaks plugin ABI version {}, this misslam speaks {}: rebuild the plugin against misslam-abi {}",
            vt.abi_version,
            abi::ABI_VERSION,
            abi::ABI_CRATE_VERSION
        ));
    }
    let theirs = read_str(vt.abi_crate_version, "abi crate version")?;
    if major_minor(&theirs) != major_minor(abi::ABI_CRATE_VERSION) {
        return Err(format!(
            "`{origin}` was built against misslam-abi {theirs}, this misslam has {}: rebuild the plugin",
            abi::ABI_CRATE_VERSION
        ));
    }
    let rustc = read_str(vt.rustc_version, "rustc version")?;
    if rustc != abi::RUSTC_VERSION {
        tracing::info!(
            "plugin `{origin}` was compiled by {rustc}, misslam by {} (fine: only C types cross)",
            abi::RUSTC_VERSION
        );
    }
    let id = read_str(vt.id, "plugin id")?;
    if id.is_empty() || !id.contains('.') {
        return Err(format!(
            "`{origin}`: plugin id `{id}` must look like `role.name`"
        ));
    }
    let params_doc = read_str(vt.params_doc, "params doc")?;
    let info = PluginInfo {
        id,
        summary: read_str(vt.summary, "summary")?,
        inputs: ports(vt.inputs, vt.n_inputs, "input")?,
        outputs: ports(vt.outputs, vt.n_outputs, "output")?,
        params: parse_params_doc(&params_doc),
        origin: origin.to_owned(),
    };
    Ok(Arc::new(DynamicPlugin { vt, info }))
}

fn major_minor(v: &str) -> (&str, &str) {
    let mut it = v.split('.');
    (it.next().unwrap_or(""), it.next().unwrap_or(""))
}

/// Lines `name: type = default; doc` (the default part optional).
fn parse_params_doc(text: &str) -> Vec<ParamDoc> {
    text.lines()
        .filter_map(|line| {
            let (name, rest) = line.split_once(':')?;
            let (head, doc) = rest.split_once(';').unwrap_or((rest, ""));
            let (ty, default) = match head.split_once('=') {
                Some((t, d)) => (t.trim().to_owned(), Some(d.trim().to_owned())),
                None => (head.trim().to_owned(), None),
            };
            Some(ParamDoc {
                name: name.trim().to_owned(),
                ty,
                default,
                doc: doc.trim().to_owned(),
            })
        })
        .collect()
}

struct DynamicPlugin {
    vt: &'static abi::PluginVTable,
    info: PluginInfo,
}

const ERR_CAP: usize = 4096;

impl DynamicPlugin {
    fn create(&self, params: &toml::Table) -> Result<*mut c_void, BuildError> {
        let text = toml::to_string(params).map_err(|e| BuildError::Failed(e.to_string()))?;
        let mut bytes = vec![0u8; ERR_CAP];
        let mut err = abi::ErrorBuf {
            ptr: bytes.as_mut_ptr(),
            cap: ERR_CAP,
            len: 0,
        };
        // SAFETY: the ABI contract; text and err outlive the call.
        let state = unsafe { (self.vt.create)(abi::Str::borrow(&text), &mut err) };
        if state.is_null() {
            let msg = String::from_utf8_lossy(&bytes[..err.len.min(ERR_CAP)]).into_owned();
            return Err(BuildError::Param {
                key: None,
                path: String::new(),
                message: if msg.is_empty() {
                    "the plugin refused its parameters".into()
                } else {
                    msg
                },
            });
        }
        Ok(state)
    }
}

impl Plugin for DynamicPlugin {
    fn info(&self) -> &PluginInfo {
        &self.info
    }

    fn check_params(&self, params: &toml::Table) -> Result<(), BuildError> {
        let state = self.create(params)?;
        // SAFETY: state came from create and is destroyed once.
        unsafe { (self.vt.destroy)(state) };
        Ok(())
    }

    fn build(
        &self,
        params: &toml::Table,
        _ctx: &BuildContext,
    ) -> Result<Box<dyn Node>, BuildError> {
        let state = self.create(params)?;
        Ok(Box::new(DynamicNode {
            vt: self.vt,
            state,
            outputs: self.info.outputs.clone(),
            staged: Vec::new(),
            err: vec![0u8; ERR_CAP],
        }))
    }
}

/// An output buffer the plugin asked for on one call.
struct Staged {
    port: u32,
    desc: abi::BufferDesc,
    data: Vec<u8>,
}

struct DynamicNode {
    vt: &'static abi::PluginVTable,
    state: *mut c_void,
    outputs: Vec<PortSpec>,
    staged: Vec<Staged>,
    err: Vec<u8>,
}

// SAFETY: the plugin state is only touched through `&mut self` (one thread at a time); the ABI
// requires plugin instances to be movable between threads.
unsafe impl Send for DynamicNode {}

struct SinkCtx<'a> {
    outputs: &'a [PortSpec],
    staged: &'a mut Vec<Staged>,
}

unsafe extern "C" fn alloc_output(
    ctx: *mut c_void,
    port: u32,
    desc: *const abi::BufferDesc,
) -> *mut u8 {
    if ctx.is_null() || desc.is_null() {
        return std::ptr::null_mut();
    }
    // SAFETY: ctx is the SinkCtx passed by `process` for the duration of the call.
    let sink = unsafe { &mut *(ctx as *mut SinkCtx) };
    // SAFETY: non-null, valid for the call.
    let desc = unsafe { *desc };
    let Some(spec) = sink.outputs.get(port as usize) else {
        return std::ptr::null_mut();
    };
    let kind_ok = matches!(
        (abi::BufferKind::from_raw(desc.kind), spec.ty),
        (Some(abi::BufferKind::Image), PortType::Image)
            | (Some(abi::BufferKind::Disparity), PortType::Disparity)
            | (Some(abi::BufferKind::Depth), PortType::Depth)
    );
    let channels_ok = match spec.ty {
        PortType::Image => desc.channels == 1 || desc.channels == 3,
        _ => desc.channels == 1,
    };
    if !kind_ok || !channels_ok || desc.width == 0 || desc.height == 0 {
        return std::ptr::null_mut();
    }
    sink.staged.retain(|s| s.port != port);
    sink.staged.push(Staged {
        port,
        desc,
        data: vec![0u8; desc.byte_len()],
    });
    sink.staged
        .last_mut()
        .map_or(std::ptr::null_mut(), |s| s.data.as_mut_ptr())
}

fn calib_to_abi(c: &StereoCalib) -> abi::Calib {
    abi::Calib {
        fx: c.fx,
        fy: c.fy,
        cx: c.cx,
        cy: c.cy,
        cx_right: c.cx_right,
        baseline_mm: c.baseline_mm,
    }
}

fn calib_from_abi(c: &abi::Calib, width: u32, height: u32) -> StereoCalib {
    StereoCalib {
        width,
        height,
        fx: c.fx,
        fy: c.fy,
        cx: c.cx,
        cy: c.cy,
        cx_right: c.cx_right,
        baseline_mm: c.baseline_mm,
    }
}

fn map_buffer(kind: abi::BufferKind, map: &FloatMap, calib: &StereoCalib) -> abi::Buffer {
    abi::Buffer {
        desc: abi::BufferDesc {
            kind: kind as u32,
            width: map.width,
            height: map.height,
            channels: 1,
            has_calib: 1,
            calib: calib_to_abi(calib),
        },
        data: map.data.as_ptr() as *const u8,
    }
}

impl Node for DynamicNode {
    fn process(
        &mut self,
        _ctx: &mut NodeContext,
        frame: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        let mut buffers = Vec::with_capacity(inputs.specs.len());
        for i in 0..inputs.specs.len() {
            let p = inputs.raw(i).ok_or_else(|| {
                NodeError::msg(format!("input `{}` received nothing", inputs.specs[i].name))
            })?;
            buffers.push(match p {
                Payload::Image(img) => abi::Buffer {
                    desc: abi::BufferDesc {
                        kind: abi::BufferKind::Image as u32,
                        width: img.width,
                        height: img.height,
                        channels: img.channels as u32,
                        has_calib: 0,
                        calib: abi::Calib::default(),
                    },
                    data: img.data.as_ptr(),
                },
                Payload::Disparity(d) => map_buffer(abi::BufferKind::Disparity, &d.map, &d.calib),
                Payload::Depth(d) => map_buffer(abi::BufferKind::Depth, &d.map, &d.calib),
                other => {
                    return Err(NodeError::msg(format!(
                        "dynamic plugins take image, disparity or depth, not {}",
                        other.port_type()
                    )))
                }
            });
        }
        self.staged.clear();
        let mut sink_ctx = SinkCtx {
            outputs: &self.outputs,
            staged: &mut self.staged,
        };
        let sink = abi::OutputSink {
            ctx: &mut sink_ctx as *mut SinkCtx as *mut c_void,
            alloc: alloc_output,
        };
        let mut err = abi::ErrorBuf {
            ptr: self.err.as_mut_ptr(),
            cap: self.err.len(),
            len: 0,
        };
        // SAFETY: the ABI contract: buffers, sink and err stay valid during the call.
        let code = unsafe {
            (self.vt.process)(
                self.state,
                frame.index,
                buffers.as_ptr(),
                buffers.len(),
                &sink,
                &mut err,
            )
        };
        let msg = || String::from_utf8_lossy(&self.err[..err.len.min(self.err.len())]).into_owned();
        match code {
            abi::OK => {}
            abi::PANICKED => return Err(NodeError::msg(format!("plugin panicked: {}", msg()))),
            _ => return Err(NodeError::msg(format!("plugin failed: {}", msg()))),
        }
        for s in self.staged.drain(..) {
            let spec = &self.outputs[s.port as usize];
            let (w, h) = (s.desc.width, s.desc.height);
            let payload = match spec.ty {
                PortType::Image => Payload::Image(Arc::new(
                    Image::new(w, h, s.desc.channels as u8, s.data).map_err(NodeError::msg)?,
                )),
                PortType::Disparity | PortType::Depth => {
                    let data: Vec<f32> = s
                        .data
                        .chunks_exact(4)
                        .map(|b| f32::from_ne_bytes([b[0], b[1], b[2], b[3]]))
                        .collect();
                    let map = FloatMap {
                        width: w,
                        height: h,
                        data,
                    };
                    let calib = calib_from_abi(&s.desc.calib, w, h);
                    if spec.ty == PortType::Depth {
                        Payload::Depth(Arc::new(DepthMap { map, calib }))
                    } else {
                        Payload::Disparity(Arc::new(DisparityMap { map, calib }))
                    }
                }
                other => {
                    return Err(NodeError::msg(format!(
                        "dynamic plugins cannot output {other}"
                    )));
                }
            };
            outputs.put_payload(&spec.name, payload)?;
        }
        Ok(Flow::Continue)
    }
}

impl Drop for DynamicNode {
    fn drop(&mut self) {
        // SAFETY: state came from create and is destroyed once.
        unsafe { (self.vt.destroy)(self.state) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn params_doc_lines() {
        let d = parse_params_doc("gain: float = 1.0; multiplies\nname: string; no default\n");
        assert_eq!(d.len(), 2);
        assert_eq!(d[0].name, "gain");
        assert_eq!(d[0].default.as_deref(), Some("1.0"));
        assert_eq!(d[1].default, None);
        assert_eq!(d[1].doc, "no default");
    }

    #[test]
    fn missing_library_is_a_clear_error() {
        let e = load_library(Path::new("/nonexistent/libplugin.so"))
            .err()
            .unwrap();
        assert!(e.contains("does not exist"), "{e}");
    }
}
