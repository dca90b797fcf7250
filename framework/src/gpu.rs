//! The GPU context: one wgpu device shared by every node, created only when a node asks for it.
//!
//! Where no adapter exists the request fails with a clear [`GpuError`]; nodes decide by their
//! `device` parameter whether that is an error or a fall-back to their CPU path ([`Device`]).
//! Mesa's software Vulkan (lavapipe) is a valid adapter, so CI runs the GPU code on the CPU.
//! Adapter choice follows wgpu's environment variables (`WGPU_BACKEND`, `WGPU_ADAPTER_NAME`);
//! without them, the primary backends (Vulkan, Metal, DX12) are tried.

use std::sync::{mpsc, Arc, OnceLock};

use wgpu::util::DeviceExt;

/// Why no GPU is available, or a GPU operation failed.
#[derive(Debug, Clone, thiserror::Error)]
pub enum GpuError {
    /// No adapter could be found or opened.
    #[error("no GPU adapter available ({0}); on Debian install mesa-vulkan-drivers and libvulkan1 for the software adapter, or set the node's `device = \"cpu\"`")]
    NoAdapter(String),
    /// A GPU operation failed.
    #[error("GPU operation failed: {0}")]
    Operation(String),
}

/// Where a node runs its work, a parameter of every node that has a GPU path.
#[derive(
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    Eq,
    serde::Serialize,
    serde::Deserialize,
    schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum Device {
    /// The CPU implementation.
    #[default]
    Cpu,
    /// The GPU implementation; an error when no adapter exists.
    Gpu,
    /// The GPU when an adapter exists, else the CPU (logged once).
    Auto,
}

/// An opened device with its queue.
pub struct GpuContext {
    /// The device.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
    /// What adapter it runs on (name, backend, device type).
    pub adapter_info: wgpu::AdapterInfo,
}

/// Hands out the shared [`GpuContext`], opening it on the first request.
#[derive(Default)]
pub struct GpuProvider {
    cell: OnceLock<Result<Arc<GpuContext>, GpuError>>,
}

impl GpuProvider {
    /// A provider that has not opened anything yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// The shared context, opened on first call. Every later call returns the same device (or the
    /// same error).
    pub fn get(&self) -> Result<Arc<GpuContext>, GpuError> {
        self.cell
            .get_or_init(|| GpuContext::open().map(Arc::new))
            .clone()
    }

    /// Resolves a node's `device` parameter: `Some(ctx)` to run on the GPU, `None` for the CPU.
    pub fn for_device(
        &self,
        device: Device,
        node: &str,
    ) -> Result<Option<Arc<GpuContext>>, GpuError> {
        match device {
            Device::Cpu => Ok(None),
            Device::Gpu => self.get().map(Some),
            Device::Auto => match self.get() {
                Ok(ctx) => Ok(Some(ctx)),
                Err(e) => {
                    tracing::warn!("node `{node}`: device = \"auto\" falls back to the CPU: {e}");
                    Ok(None)
                }
            },
        }
    }

    /// True when a context has been opened.
    pub fn is_open(&self) -> bool {
        matches!(self.cell.get(), Some(Ok(_)))
    }
}

/// The instance's settings: the primary backends (Vulkan, Metal, DX12) unless `WGPU_BACKEND`
/// names others. wgpu's default would add OpenGL, whose compute path (GLSL through naga) gave
/// the SGM kernels 1,379 of 3,840 pixels of another validity than the CPU on Mesa's llvmpipe,
/// where lavapipe's Vulkan gives none: on a machine with only OpenGL the nodes therefore find
/// no adapter and say so (or fall back to the CPU with `device = "auto"`) rather than compute
/// wrong depth.
fn instance_descriptor() -> wgpu::InstanceDescriptor {
    wgpu::InstanceDescriptor {
        backends: wgpu::Backends::PRIMARY,
        ..wgpu::InstanceDescriptor::new_without_display_handle()
    }
    .with_env()
}

impl GpuContext {
    /// Opens the best adapter wgpu finds (high performance preferred).
    pub fn open() -> Result<Self, GpuError> {
        let instance = wgpu::Instance::new(instance_descriptor());
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            ..Default::default()
        }))
        .map_err(|e| GpuError::NoAdapter(e.to_string()))?;
        let adapter_info = adapter.get_info();
        let limits = wgpu::Limits::downlevel_defaults().using_resolution(adapter.limits());
        let limits = wgpu::Limits {
            max_storage_buffer_binding_size: adapter.limits().max_storage_buffer_binding_size,
            max_buffer_size: adapter.limits().max_buffer_size,
            max_compute_workgroup_storage_size: adapter.limits().max_compute_workgroup_storage_size,
            max_compute_invocations_per_workgroup: adapter
                .limits()
                .max_compute_invocations_per_workgroup,
            max_compute_workgroup_size_x: adapter.limits().max_compute_workgroup_size_x,
            max_storage_buffers_per_shader_stage: adapter
                .limits()
                .max_storage_buffers_per_shader_stage,
            ..limits
        };
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("misslam"),
            // Timestamps time the GPU stages where the adapter has them; subgroups let kernels
            // exchange values between invocations without workgroup memory and barriers; 64-bit
            // atomics add four u16 lanes at once.
            required_features: adapter.features()
                & (wgpu::Features::TIMESTAMP_QUERY
                    | wgpu::Features::SUBGROUP
                    | wgpu::Features::SHADER_INT64
                    | wgpu::Features::SHADER_INT64_ATOMIC_ALL_OPS),
            required_limits: limits,
            ..Default::default()
        }))
        .map_err(|e| {
            GpuError::NoAdapter(format!(
                "{} could not open a device: {e}",
                adapter_info.name
            ))
        })?;
        tracing::info!(
            "GPU: {} ({:?}, {:?})",
            adapter_info.name,
            adapter_info.backend,
            adapter_info.device_type
        );
        Ok(GpuContext {
            device,
            queue,
            adapter_info,
        })
    }

    /// The size of every subgroup of this device's compute kernels, where the device has
    /// subgroups ([`wgpu::Features::SUBGROUP`]) and they all have one size; `None` otherwise.
    pub fn subgroup_size(&self) -> Option<u32> {
        let info = &self.adapter_info;
        (self.device.features().contains(wgpu::Features::SUBGROUP)
            && info.subgroup_min_size == info.subgroup_max_size)
            .then_some(info.subgroup_min_size)
    }

    /// True where kernels may add to 64-bit integers atomically in storage buffers.
    pub fn has_int64_atomics(&self) -> bool {
        self.device
            .features()
            .contains(wgpu::Features::SHADER_INT64 | wgpu::Features::SHADER_INT64_ATOMIC_ALL_OPS)
    }

    /// True on a discrete GPU (not an integrated, virtual or software adapter).
    pub fn is_discrete(&self) -> bool {
        self.adapter_info.device_type == wgpu::DeviceType::DiscreteGpu
    }

    /// A buffer of `size` bytes (at least 16, so that an empty image still binds) for `usage`.
    pub fn buffer(&self, label: &str, size: u64, usage: wgpu::BufferUsages) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: size.max(16),
            usage,
            mapped_at_creation: false,
        })
    }

    /// Compiles a WGSL compute shader into a pipeline with an automatic layout.
    pub fn compute_pipeline(&self, label: &str, wgsl: &str, entry: &str) -> wgpu::ComputePipeline {
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(label),
                source: wgpu::ShaderSource::Wgsl(wgsl.into()),
            });
        self.device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(label),
                layout: None,
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
    }

    /// A bind group of `buffers` at bindings 0, 1, 2, ... of group 0 of `pipeline`.
    pub fn bind_buffers(
        &self,
        pipeline: &wgpu::ComputePipeline,
        label: &str,
        buffers: &[&wgpu::Buffer],
    ) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry> = buffers
            .iter()
            .enumerate()
            .map(|(i, b)| wgpu::BindGroupEntry {
                binding: i as u32,
                resource: b.as_entire_binding(),
            })
            .collect();
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(label),
            layout: &pipeline.get_bind_group_layout(0),
            entries: &entries,
        })
    }

    /// Binds `buffers` to bindings 0, 1, 2, ... of group 0 of `pipeline`, dispatches `groups`
    /// workgroups and submits: one kernel launch.
    pub fn dispatch(
        &self,
        pipeline: &wgpu::ComputePipeline,
        label: &str,
        buffers: &[&wgpu::Buffer],
        groups: (u32, u32, u32),
    ) {
        let bind = self.bind_buffers(pipeline, label, buffers);
        let mut enc = self.device.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(groups.0, groups.1, groups.2);
        }
        self.queue.submit(Some(enc.finish()));
    }

    /// Waits until everything submitted so far has run (for per-stage timings).
    pub fn wait(&self) -> Result<(), GpuError> {
        self.device
            .poll(wgpu::PollType::Wait {
                submission_index: None,
                timeout: None,
            })
            .map(|_| ())
            .map_err(|e| GpuError::Operation(e.to_string()))
    }

    /// Copies `size` bytes of a `COPY_SRC` buffer back to the host and waits for them.
    pub fn read_back(&self, src: &wgpu::Buffer, size: u64) -> Result<Vec<u8>, GpuError> {
        let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut enc = self.device.create_command_encoder(&Default::default());
        enc.copy_buffer_to_buffer(src, 0, &staging, 0, size);
        self.queue.submit(Some(enc.finish()));
        let slice = staging.slice(..);
        let (tx, rx) = mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.device
            .poll(wgpu::PollType::Wait {
                submission_index: None,
                timeout: None,
            })
            .map_err(|e| GpuError::Operation(e.to_string()))?;
        rx.recv()
            .map_err(|e| GpuError::Operation(e.to_string()))?
            .map_err(|e| GpuError::Operation(e.to_string()))?;
        let data = slice
            .get_mapped_range()
            .map_err(|e| GpuError::Operation(e.to_string()))?
            .to_vec();
        staging.unmap();
        Ok(data)
    }
}

/// The WGSL source of a kernel that names shared files by lines `// uses: FILE.wgsl`: its
/// `enable ...;` directives (which WGSL wants first), then each used file as `files` gives it
/// (name, source), in the order of those lines, then the rest of the kernel. A used file does
/// not use others. The shader test assembles every kernel so before it validates it.
pub fn wgsl_with_uses(src: &str, files: &[(&str, &str)]) -> Result<String, String> {
    let mut head = String::new();
    let mut shared = String::new();
    let mut body = String::new();
    for line in src.lines() {
        let trimmed = line.trim();
        if let Some(name) = trimmed.strip_prefix("// uses:") {
            let name = name.trim();
            let (_, used) = files
                .iter()
                .find(|(n, _)| *n == name)
                .ok_or_else(|| format!("the kernel uses `{name}`, which is not among its files"))?;
            if used.lines().any(|l| l.trim().starts_with("// uses:")) {
                return Err(format!("`{name}` uses other files: only kernels may"));
            }
            shared.push_str(used);
            shared.push('\n');
        } else if trimmed.starts_with("enable ") {
            head.push_str(line);
            head.push('\n');
        } else {
            body.push_str(line);
            body.push('\n');
        }
    }
    Ok(head + &shared + &body)
}

/// WGSL of the RGB-to-gray kernel.
pub const GRAY_WGSL: &str = include_str!("../../shaders/image/gray.wgsl");

/// RGB to BT.601 gray on the GPU, bit-exact with [`crate::payload::luma_bt601`].
pub struct GrayKernel {
    pipeline: wgpu::ComputePipeline,
}

impl GrayKernel {
    /// Compiles the kernel.
    pub fn new(ctx: &GpuContext) -> Self {
        GrayKernel {
            pipeline: ctx.compute_pipeline("gray", GRAY_WGSL, "main"),
        }
    }

    /// Converts interleaved RGB bytes (3 per pixel) to gray, upload and readback included.
    pub fn run(&self, ctx: &GpuContext, rgb: &[u8]) -> Result<Vec<u8>, GpuError> {
        if !rgb.len().is_multiple_of(3) {
            return Err(GpuError::Operation(format!(
                "RGB buffer of {} bytes is not a whole number of pixels",
                rgb.len()
            )));
        }
        let pixels = rgb.len() / 3;
        if pixels == 0 {
            return Ok(Vec::new());
        }
        let quads = pixels.div_ceil(4);
        let mut padded = Vec::with_capacity(rgb.len().div_ceil(4) * 4);
        padded.extend_from_slice(rgb);
        padded.resize(rgb.len().div_ceil(4) * 4, 0);
        let params: [u32; 4] = [pixels as u32, 0, 0, 0];
        let dev = &ctx.device;
        let params_buf = dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("gray params"),
            contents: bytemuck::cast_slice(&params),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let in_buf = dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("gray rgb"),
            contents: &padded,
            usage: wgpu::BufferUsages::STORAGE,
        });
        let out_size = (quads * 4) as u64;
        let out_buf = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("gray out"),
            size: out_size,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        ctx.dispatch(
            &self.pipeline,
            "gray",
            &[&params_buf, &in_buf, &out_buf],
            ((quads as u32).div_ceil(64), 1, 1),
        );
        let mut out = ctx.read_back(&out_buf, out_size)?;
        out.truncate(pixels);
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_kernel_gets_its_used_files_after_its_directives() {
        let kernel = "enable subgroups;\n// uses: a.wgsl\nfn main() {}\n";
        let src = super::wgsl_with_uses(kernel, &[("a.wgsl", "const A: u32 = 1u;")]).unwrap();
        assert_eq!(
            src, "enable subgroups;\nconst A: u32 = 1u;\nfn main() {}\n",
            "directive, used file, kernel"
        );
        let err = super::wgsl_with_uses(kernel, &[]).unwrap_err();
        assert!(err.contains("a.wgsl"), "{err}");
        let nested = super::wgsl_with_uses(kernel, &[("a.wgsl", "// uses: b.wgsl")]).unwrap_err();
        assert!(nested.contains("only kernels"), "{nested}");
    }

    #[test]
    fn only_the_primary_backends_unless_the_environment_names_others() {
        if std::env::var_os("WGPU_BACKEND").is_some() {
            eprintln!("skipped: WGPU_BACKEND is set, so it decides the backends");
            return;
        }
        let backends = super::instance_descriptor().backends;
        assert_eq!(backends, wgpu::Backends::PRIMARY);
        assert!(!backends.contains(wgpu::Backends::GL));
    }
}
