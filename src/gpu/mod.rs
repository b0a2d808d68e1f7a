//! The GPU tracer (wgpu compute, WGSL): the brickmap traversal of
//! [`crate::trace`] ported to a compute shader, over the same grid, occupancy
//! layer, masks and material arena.
//!
//! On a machine without a GPU, wgpu runs on Mesa's lavapipe (software
//! Vulkan). With no adapter at all, [`GpuContext::new`] returns
//! [`GpuError::NoAdapter`] and callers fall back to the CPU tracer.

use bytemuck::{Pod, Zeroable};
use glam::{DVec3, IVec3};
use thiserror::Error;
use wgpu::util::DeviceExt;

use crate::trace::{Camera, Frame, RenderOptions};
use crate::world::{BRICK_SHIFT, BrickGrid, BrickPool, Palette};

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
    /// The device was lost or a transfer failed.
    #[error("GPU failure: {0}")]
    Runtime(String),
}

/// An adapter, device and queue.
pub struct GpuContext {
    /// The device.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
    /// What the adapter is (name, backend, device type).
    pub info: wgpu::AdapterInfo,
    limits: wgpu::Limits,
}

impl GpuContext {
    /// Open the best available adapter (a real GPU, else lavapipe).
    pub fn new() -> Result<Self, GpuError> {
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
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("brickworld"),
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device(e.to_string()))?;
        Ok(GpuContext {
            device,
            queue,
            info,
            limits,
        })
    }

    /// One line describing the adapter.
    pub fn describe(&self) -> String {
        format!(
            "{} ({:?}, {:?})",
            self.info.name, self.info.backend, self.info.device_type
        )
    }
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Params {
    eye: [f32; 3],
    tan_half: f32,
    f: [f32; 3],
    aspect: f32,
    r: [f32; 3],
    ambient: f32,
    u: [f32; 3],
    shadows: u32,
    light: [f32; 3],
    width: u32,
    dims: [i32; 3],
    height: u32,
    anchor: [i32; 3],
    _pad: u32,
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable, Debug)]
struct PixelOut {
    rgba: u32,
    depth: f32,
    vx: i32,
    vy: i32,
    vz: i32,
    normal: u32,
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
    /// Row-major hit voxel and face normal.
    pub hits: Vec<Option<(IVec3, IVec3)>>,
}

/// The brickmap uploaded to the GPU, with its compute pipeline.
pub struct GpuBrickmap {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    buffers: [wgpu::Buffer; 6],
    frame: Frame,
    dims: IVec3,
}

fn words_of(bytes: &[u8]) -> Vec<u32> {
    bytes
        .chunks(4)
        .map(|c| {
            c.iter()
                .enumerate()
                .fold(0u32, |w, (i, b)| w | (*b as u32) << (8 * i))
        })
        .collect()
}

impl GpuBrickmap {
    /// Upload `grid` (with `pool`'s bricks) and `palette`, and build the pipeline.
    pub fn new(
        ctx: &GpuContext,
        grid: &BrickGrid,
        pool: &BrickPool,
        palette: &Palette,
    ) -> Result<Self, GpuError> {
        let dev = &ctx.device;
        let (masks, meta, arena) = pool.raw();
        let occ: Vec<u32> = grid
            .occupancy_words()
            .iter()
            .flat_map(|w| [*w as u32, (*w >> 32) as u32])
            .collect();
        let mask_words: Vec<u32> = masks
            .iter()
            .flat_map(|m| m.iter().flat_map(|w| [*w as u32, (*w >> 32) as u32]))
            .collect();
        let meta_words: Vec<u32> = meta.iter().flat_map(|m| *m).collect();
        let arena_words = words_of(arena);
        let pal: Vec<u32> = (0..=255u8)
            .map(|m| {
                let c = palette.rgb(m);
                c[0] as u32 | (c[1] as u32) << 8 | (c[2] as u32) << 16
            })
            .collect();
        let limit = ctx.limits.max_storage_buffer_binding_size;
        let pad = |v: Vec<u32>| if v.is_empty() { vec![0u32] } else { v };
        let contents: [(&'static str, Vec<u32>); 6] = [
            ("brick grid", grid.pointers().to_vec()),
            ("occupancy layer", occ),
            ("brick masks", mask_words),
            ("brick metadata", meta_words),
            ("material arena", arena_words),
            ("palette", pal),
        ];
        for (what, v) in &contents {
            let needed = v.len() as u64 * 4;
            if needed > limit {
                return Err(GpuError::TooLarge {
                    what,
                    needed,
                    limit,
                });
            }
        }
        let buffers = contents.map(|(what, v)| {
            dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(what),
                contents: bytemuck::cast_slice(&pad(v)),
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            })
        });
        let scope = dev.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = dev.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("brickmap.wgsl"),
            source: wgpu::ShaderSource::Wgsl(include_str!("brickmap.wgsl").into()),
        });
        let storage = |binding: u32, read_only: bool| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Storage { read_only },
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        let mut entries = vec![wgpu::BindGroupLayoutEntry {
            binding: 0,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        }];
        entries.extend((1..=6).map(|b| storage(b, true)));
        entries.push(storage(7, false));
        let layout = dev.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("brickmap"),
            entries: &entries,
        });
        let pl = dev.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("brickmap"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = dev.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("brickmap"),
            layout: Some(&pl),
            module: &module,
            entry_point: Some("main"),
            compilation_options: Default::default(),
            cache: None,
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Shader(e.to_string()));
        }
        Ok(GpuBrickmap {
            pipeline,
            layout,
            buffers,
            frame: Frame {
                anchor: grid.origin() << BRICK_SHIFT,
            },
            dims: grid.dims() << BRICK_SHIFT,
        })
    }

    /// Render `camera`'s view.
    pub fn render(
        &self,
        ctx: &GpuContext,
        camera: &Camera,
        opts: &RenderOptions,
    ) -> Result<GpuFrame, GpuError> {
        let dev = &ctx.device;
        let (w, h) = (camera.width, camera.height);
        let f = (camera.target - camera.eye).normalize();
        let r = f.cross(DVec3::Y).normalize();
        let u = r.cross(f);
        let params = Params {
            eye: self.frame.to_local(camera.eye).to_array(),
            tan_half: (camera.fov_deg.to_radians() * 0.5).tan() as f32,
            f: f.as_vec3().to_array(),
            aspect: w as f32 / h as f32,
            r: r.as_vec3().to_array(),
            ambient: opts.shading.ambient,
            u: u.as_vec3().to_array(),
            shadows: opts.shadows as u32,
            light: opts.shading.light.to_array(),
            width: w,
            dims: self.dims.to_array(),
            height: h,
            anchor: self.frame.anchor.to_array(),
            _pad: 0,
        };
        let pixels = (w * h) as u64;
        let out_size = pixels * std::mem::size_of::<PixelOut>() as u64;
        let uniform = dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("params"),
            contents: bytemuck::bytes_of(&params),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let out = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("pixels"),
            size: out_size,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let staging = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size: out_size,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut entries = vec![wgpu::BindGroupEntry {
            binding: 0,
            resource: uniform.as_entire_binding(),
        }];
        for (i, b) in self.buffers.iter().enumerate() {
            entries.push(wgpu::BindGroupEntry {
                binding: i as u32 + 1,
                resource: b.as_entire_binding(),
            });
        }
        entries.push(wgpu::BindGroupEntry {
            binding: 7,
            resource: out.as_entire_binding(),
        });
        let bind = dev.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("brickmap"),
            layout: &self.layout,
            entries: &entries,
        });
        let mut enc = dev.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("frame"),
        });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("trace"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(w.div_ceil(8), h.div_ceil(8), 1);
        }
        enc.copy_buffer_to_buffer(&out, 0, &staging, 0, out_size);
        ctx.queue.submit([enc.finish()]);
        let slice = staging.slice(..);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        dev.poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Runtime(e.to_string()))?;
        rx.recv()
            .map_err(|e| GpuError::Runtime(e.to_string()))?
            .map_err(|e| GpuError::Runtime(e.to_string()))?;
        let data = slice
            .get_mapped_range()
            .map_err(|e| GpuError::Runtime(e.to_string()))?;
        let px: &[PixelOut] = bytemuck::cast_slice(&data);
        let mut frame = GpuFrame {
            width: w,
            height: h,
            rgb: Vec::with_capacity(pixels as usize * 3),
            depth: Vec::with_capacity(pixels as usize),
            hits: Vec::with_capacity(pixels as usize),
        };
        for p in px {
            frame
                .rgb
                .extend_from_slice(&[p.rgba as u8, (p.rgba >> 8) as u8, (p.rgba >> 16) as u8]);
            if p.normal == 0 {
                frame.depth.push(f32::INFINITY);
                frame.hits.push(None);
            } else {
                frame.depth.push(p.depth);
                let mut n = IVec3::ZERO;
                if p.normal != 7 {
                    let axis = ((p.normal - 1) / 2) as usize;
                    n[axis] = if (p.normal - 1) % 2 == 1 { 1 } else { -1 };
                }
                frame.hits.push(Some((IVec3::new(p.vx, p.vy, p.vz), n)));
            }
        }
        drop(data);
        staging.unmap();
        Ok(frame)
    }
}
