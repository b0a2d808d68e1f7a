//! The GPU tracer (wgpu compute, WGSL): the brickmap traversal of
//! [`crate::trace`] ported to a compute shader, over the same grid, occupancy
//! layer, masks and material arena.
//!
//! On a machine without a GPU, wgpu runs on Mesa's lavapipe (software
//! Vulkan). With no adapter at all, [`GpuContext::new`] returns
//! [`GpuError::NoAdapter`] and callers fall back to the CPU tracer.

mod frame;
mod stream;
mod tracer;

use glam::IVec3;
use thiserror::Error;

pub use stream::{FrameStats, MAX_POOL_SLOTS, StreamConfig, fit_pool};
pub use tracer::GpuBrickmap;

/// Errors of the GPU subsystem.
#[derive(Debug, Error)]
pub enum GpuError {
    /// No adapter was found (no GPU and no software Vulkan).
    #[error("no GPU adapter found (install mesa-vulkan-drivers for the lavapipe software device)")]
    NoAdapter,
    /// The device could not be created.
    #[error("cannot create the GPU device: {0}")]
    Device(String),
    /// The shader or pipeline failed validation.
    #[error("GPU shader or pipeline failed validation: {0}")]
    Shader(String),
    /// The scene does not fit the device's limits.
    #[error("the scene does not fit the GPU: {what} needs {needed} bytes, the limit is {limit}")]
    TooLarge {
        /// Which buffer.
        what: &'static str,
        /// Bytes needed.
        needed: u64,
        /// The device limit.
        limit: u64,
    },
    /// A frame's per-pixel buffer does not fit the device's limits.
    #[error(
        "a {width}x{height} frame needs {needed} bytes of GPU pixel buffer, over this device's limit of {limit}: render a smaller image"
    )]
    FrameTooLarge {
        /// Frame width.
        width: u32,
        /// Frame height.
        height: u32,
        /// Bytes needed.
        needed: u64,
        /// The device limit.
        limit: u64,
    },
    /// The device was lost or a transfer failed.
    #[error("GPU failure: {0}")]
    Runtime(String),
}

/// Where frames are traced (`render.tracer`, `--tracer`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum TracerChoice {
    /// The GPU, unless the only adapter is a software rasterizer (lavapipe,
    /// llvmpipe, WARP), where the CPU tracer is faster.
    #[default]
    Auto,
    /// The GPU, whatever it is (falling back to the CPU without one).
    Gpu,
    /// The CPU tracer.
    Cpu,
}

impl std::str::FromStr for TracerChoice {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(TracerChoice::Auto),
            "gpu" => Ok(TracerChoice::Gpu),
            "cpu" => Ok(TracerChoice::Cpu),
            other => Err(format!("'{other}' is not auto, gpu or cpu")),
        }
    }
}

impl std::fmt::Display for TracerChoice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            TracerChoice::Auto => "auto",
            TracerChoice::Gpu => "gpu",
            TracerChoice::Cpu => "cpu",
        })
    }
}

/// Open the GPU `choice` asks for, if any: the context (None: trace on the
/// CPU) and one line saying which tracer was chosen and why. `forced_by`
/// names what overrides `auto` where the caller is (`` `--tracer gpu` ``
/// for `render`, the world config's field for the daemon).
///
/// `auto` refuses a software rasterizer: on this project's machine lavapipe
/// traces the 2048² terrain at 2.0 Mrays/s against the CPU tracer's 6.3
/// (README, "GPU tracer and streaming").
pub fn choose(choice: TracerChoice, forced_by: &str) -> (Option<GpuContext>, String) {
    if choice == TracerChoice::Cpu {
        return (None, "tracer: cpu (as configured)".into());
    }
    match (GpuContext::new(), choice) {
        (Ok(ctx), TracerChoice::Auto) if ctx.is_software() => (
            None,
            format!(
                "tracer: cpu (auto: the only GPU adapter, {}, is a software rasterizer, where the CPU tracer is faster; {forced_by} forces it)",
                ctx.describe()
            ),
        ),
        (Ok(ctx), _) => {
            let line = format!("tracer: gpu ({choice}: {})", ctx.describe());
            (Some(ctx), line)
        }
        (Err(e), _) => (None, format!("tracer: cpu ({choice}: {e})")),
    }
}

/// An adapter, device and queue.
pub struct GpuContext {
    /// The device.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
    /// What the adapter is (name, backend, device type).
    pub info: wgpu::AdapterInfo,
    pub(crate) limits: wgpu::Limits,
    /// Whether the device writes timestamps at pass boundaries (frames
    /// then report the tracer's own time, [`FrameStats::gpu_ms`]).
    pub(crate) timestamps: bool,
}

/// The least address space left (under `ulimit -v`) in which a GPU device
/// is opened.
pub const MIN_GPU_ADDRESS_SPACE: u64 = 1 << 30;

/// Threads a GPU device needs besides one per core (the driver's own, and
/// the process's), where the user's threads are limited.
pub const MIN_GPU_SPARE_THREADS: u64 = 8;

impl GpuContext {
    /// Open the best available adapter (a real GPU, else lavapipe).
    pub fn new() -> Result<Self, GpuError> {
        // Mesa's lavapipe fails to create its device below about 870 MB of
        // address space, and at one limit near 490 MiB it crashed the
        // process in its own thread (SIGSEGV, hostile environment probe):
        // with less than this left the GPU is not tried.
        if let Some(left) = crate::scene::budget::address_space_left()
            && left < MIN_GPU_ADDRESS_SPACE
        {
            return Err(GpuError::Device(format!(
                "only {} of address space is left (ulimit -v); the GPU driver needs about {}",
                crate::scene::budget::human(left),
                crate::scene::budget::human(MIN_GPU_ADDRESS_SPACE)
            )));
        }
        // Lavapipe starts a worker thread per core and, when it cannot
        // (the user at `ulimit -u`), waits for them for ever: `render
        // --tracer gpu` hung (regression, review of the environment
        // probe's fixes). With too few threads left the GPU is not tried.
        // Lavapipe's workers: one per core, or `LP_NUM_THREADS` (review:
        // with 16 asked for, it hung where the guard counted 2 cores).
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get()) as u64;
        let cores = std::env::var("LP_NUM_THREADS")
            .ok()
            .and_then(|v| v.trim().parse::<u64>().ok())
            .map_or(cores, |n| n.max(cores));
        if let Some(left) = crate::scene::budget::threads_left()
            && left < cores + MIN_GPU_SPARE_THREADS
        {
            return Err(GpuError::Device(format!(
                "only {left} more threads may start (ulimit -u); the GPU driver needs about {}",
                cores + MIN_GPU_SPARE_THREADS
            )));
        }
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
            backends: wgpu::Backends::VULKAN,
            ..wgpu::InstanceDescriptor::new_without_display_handle()
        });
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: false,
            compatible_surface: None,
            apply_limit_buckets: false,
        }))
        .map_err(|_| GpuError::NoAdapter)?;
        let info = adapter.get_info();
        let limits = adapter.limits();
        // Timestamps only measure (`bench gpu`); a device without them
        // renders the same frames.
        let timestamps = adapter.features().contains(wgpu::Features::TIMESTAMP_QUERY);
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("brickworld"),
            required_limits: limits.clone(),
            required_features: if timestamps {
                wgpu::Features::TIMESTAMP_QUERY
            } else {
                wgpu::Features::empty()
            },
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device(e.to_string()))?;
        Ok(GpuContext {
            device,
            queue,
            info,
            limits,
            timestamps,
        })
    }

    /// Compile WGSL `source` on this device, returning validation errors as
    /// [`GpuError::Shader`] (with the compiler's message and location).
    pub fn validate_shader(&self, label: &str, source: &str) -> Result<(), GpuError> {
        let scope = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let _module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(label),
                source: wgpu::ShaderSource::Wgsl(source.into()),
            });
        match pollster::block_on(scope.pop()) {
            Some(e) => Err(GpuError::Shader(e.to_string())),
            None => Ok(()),
        }
    }

    /// Whether frames report the tracer's device time
    /// ([`FrameStats::gpu_ms`], [`GpuBrickmap::sustained_ms`]).
    pub fn has_timestamps(&self) -> bool {
        self.timestamps
    }

    /// Whether the adapter is a software rasterizer (lavapipe, llvmpipe,
    /// WARP: wgpu reports them as CPU devices).
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// One line describing the adapter.
    pub fn describe(&self) -> String {
        format!(
            "{} ({:?}, {:?})",
            self.info.name, self.info.backend, self.info.device_type
        )
    }
}

/// A frame rendered on the GPU.
#[derive(Clone, Debug)]
pub struct GpuFrame {
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
    /// Row-major RGB8.
    pub rgb: Vec<u8>,
    /// Row-major depth (t), +inf for a miss.
    pub depth: Vec<f32>,
    /// Row-major hit voxel and face normal (for a brick shown by its LOD
    /// colour: the first voxel the ray entered in it).
    pub hits: Vec<Option<(IVec3, IVec3)>>,
    /// Pixels showing a brick by its LOD colour (not yet loaded).
    pub lod_pixels: u32,
    /// Row-major: whether the pixel shows a brick by its LOD colour.
    pub lod: Vec<bool>,
}

impl GpuContext {
    /// Whether a `w`×`h` frame of [`GpuBrickmap::render`] (every output,
    /// the larger need) fits this device's buffers: a
    /// [`GpuError::FrameTooLarge`] naming the figures if not. Benchmarks
    /// ask before building a world.
    pub fn check_frame(&self, w: u32, h: u32) -> Result<(), GpuError> {
        let px = frame::PIXEL_BYTES;
        self.check_frame_bytes(w, h, w as u64 * h as u64 * px)
    }

    pub(crate) fn check_frame_bytes(&self, w: u32, h: u32, needed: u64) -> Result<(), GpuError> {
        let limit = self
            .limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size);
        if needed > limit {
            return Err(GpuError::FrameTooLarge {
                width: w,
                height: h,
                needed,
                limit,
            });
        }
        Ok(())
    }
}
