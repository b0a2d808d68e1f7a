//! The GPU brickmap: buffers, the compute pipeline, one frame's dispatch and
//! readback, and ray-guided streaming of bricks into a bounded GPU pool.
//!
//! Two ways to fill the pool:
//! - [`GpuBrickmap::preloaded`]: every brick uploaded up front (still images,
//!   parity tests);
//! - [`GpuBrickmap::streaming`]: every mixed brick starts *unloaded*; rays that
//!   reach one shade it with its LOD colour and request it; after each frame at
//!   most `uploads_per_frame` requested bricks are uploaded into free slots,
//!   evicting the least recently seen bricks when the pool is full.

use bytemuck::{Pod, Zeroable};
use glam::{DVec3, IVec3};
use rustc_hash::FxHashMap;
use wgpu::util::DeviceExt;

use super::{GpuContext, GpuError, GpuFrame};
use crate::trace::{Camera, Frame, RenderOptions};
use crate::world::{
    BRICK_SHIFT, BRICK_VOXELS, BrickContent, BrickGrid, BrickPool, Palette, UNIFORM,
};

const UNLOADED: u32 = 0x4000_0000;
const REQUESTED: u32 = 0x8000_0000;
const UNIFORM_GPU: u32 = 0xC000_0000;
const STATE_MASK: u32 = 0xC000_0000;

/// Sizes of the streaming pool.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StreamConfig {
    /// Brick slots in the GPU pool.
    pub pool_slots: u32,
    /// Bytes of material data in the GPU pool.
    pub arena_bytes: u32,
    /// Requests the feedback buffer holds per frame.
    pub feedback_capacity: u32,
    /// Most bricks uploaded per frame.
    pub uploads_per_frame: u32,
}

impl Default for StreamConfig {
    fn default() -> Self {
        StreamConfig {
            pool_slots: 65_536,
            arena_bytes: 65_536 * 96,
            feedback_capacity: 4096,
            uploads_per_frame: 256,
        }
    }
}

/// What one streamed frame did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FrameStats {
    /// Distinct bricks requested by rays this frame (recorded).
    pub requests: u32,
    /// Requests lost to feedback overflow (asked again later).
    pub overflowed: u32,
    /// Bricks uploaded after the frame.
    pub uploads: u32,
    /// Bricks evicted to make room.
    pub evictions: u32,
    /// Bricks resident after the frame.
    pub resident: u32,
    /// Bytes uploaded after the frame.
    pub upload_bytes: u64,
    /// Material bytes the uploads would have needed without culling the
    /// materials of voxels hidden on all six sides.
    pub unculled_material_bytes: u64,
    /// Material bytes actually uploaded.
    pub material_bytes: u64,
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
    frame: u32,
    feedback_capacity: u32,
    _pad: [u32; 3],
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

/// Residency bookkeeping of a streaming pool.
struct Residency {
    mirror: BrickPool,
    /// Grid index of the brick in each GPU slot.
    owner: FxHashMap<u32, u32>,
    /// GPU slot (as a mirror id) of each resident grid index.
    slot_of: FxHashMap<u32, crate::world::BrickId>,
    /// LOD colour (RGB565, from the world's palette) of each resident grid index.
    lod_of: FxHashMap<u32, u32>,
    last_seen: Vec<u32>,
    cfg: StreamConfig,
}

/// The brickmap on the GPU.
pub struct GpuBrickmap {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    grid: wgpu::Buffer,
    occ: wgpu::Buffer,
    masks: wgpu::Buffer,
    meta: wgpu::Buffer,
    arena: wgpu::Buffer,
    palette: wgpu::Buffer,
    feedback: wgpu::Buffer,
    last_seen: wgpu::Buffer,
    /// CPU copy of the grid pointers as the GPU holds them.
    shadow: Vec<u32>,
    residency: Option<Residency>,
    feedback_capacity: u32,
    frame_no: u32,
    frame: Frame,
    dims: IVec3,
    slots: u32,
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

fn lod565(c: [u8; 3]) -> u32 {
    ((c[0] as u32 >> 3) << 11) | ((c[1] as u32 >> 2) << 5) | (c[2] as u32 >> 3)
}

/// Bytes of per-voxel material data a brick needs in the pool's arena
/// (header, local palette and packed indices, rounded to the 16-byte class).
fn material_bytes(b: &crate::world::Brick) -> u64 {
    if b.local_palette().len() <= 1 {
        return 0;
    }
    let len =
        3 + b.local_palette().len() + (b.solid_voxels() as usize * b.bits() as usize).div_ceil(8);
    len.div_ceil(16) as u64 * 16
}

/// Give voxels hidden on all six sides (within the brick) the brick's most
/// common visible material: rays from outside never see them, and fewer
/// distinct materials mean a smaller palette and fewer index bits (the
/// thesis culls hidden voxels' colours the same way, §4.2). The mask is
/// untouched, so traversal is exact. Neighbours in other bricks count as
/// open, so no visible voxel is ever changed.
fn cull_hidden_materials(dense: &mut [u8; BRICK_VOXELS]) {
    let at = |d: &[u8; BRICK_VOXELS], x: i32, y: i32, z: i32| -> bool {
        (0..8).contains(&x)
            && (0..8).contains(&y)
            && (0..8).contains(&z)
            && d[(x | (y << 3) | (z << 6)) as usize] != 0
    };
    let mut hidden = [false; BRICK_VOXELS];
    let mut counts = [0u32; 256];
    for i in 0..BRICK_VOXELS {
        if dense[i] == 0 {
            continue;
        }
        let (x, y, z) = ((i & 7) as i32, ((i >> 3) & 7) as i32, (i >> 6) as i32);
        hidden[i] = at(dense, x - 1, y, z)
            && at(dense, x + 1, y, z)
            && at(dense, x, y - 1, z)
            && at(dense, x, y + 1, z)
            && at(dense, x, y, z - 1)
            && at(dense, x, y, z + 1);
        if !hidden[i] {
            counts[dense[i] as usize] += 1;
        }
    }
    let Some(common) = (1..256)
        .max_by_key(|&m| (counts[m], std::cmp::Reverse(m)))
        .filter(|&m| counts[m] > 0)
    else {
        return;
    };
    for i in 0..BRICK_VOXELS {
        if hidden[i] {
            dense[i] = common as u8;
        }
    }
}

fn occupancy_words(grid: &BrickGrid) -> Vec<u32> {
    grid.occupancy_words()
        .iter()
        .flat_map(|w| [*w as u32, (*w >> 32) as u32])
        .collect()
}

impl GpuBrickmap {
    /// Upload every brick of `grid` (from `pool`) up front.
    pub fn preloaded(
        ctx: &GpuContext,
        grid: &BrickGrid,
        pool: &BrickPool,
        palette: &Palette,
    ) -> Result<Self, GpuError> {
        let (masks, meta, arena) = pool.raw();
        let shadow: Vec<u32> = grid
            .pointers()
            .iter()
            .map(|&p| {
                if p == 0 {
                    0
                } else if p & UNIFORM != 0 {
                    UNIFORM_GPU | (p & 0xff)
                } else {
                    p
                }
            })
            .collect();
        let mask_words: Vec<u32> = masks
            .iter()
            .flat_map(|m| m.iter().flat_map(|w| [*w as u32, (*w >> 32) as u32]))
            .collect();
        let meta_words: Vec<u32> = meta.iter().flat_map(|m| *m).collect();
        Self::build(
            ctx,
            grid,
            palette,
            shadow,
            mask_words,
            meta_words,
            words_of(arena),
            masks.len() as u32,
            None,
            1,
        )
    }

    /// Start streaming: every mixed brick unloaded, carrying its LOD colour.
    pub fn streaming(
        ctx: &GpuContext,
        grid: &BrickGrid,
        pool: &BrickPool,
        palette: &Palette,
        cfg: StreamConfig,
    ) -> Result<Self, GpuError> {
        if cfg.pool_slots == 0 || cfg.feedback_capacity == 0 || cfg.uploads_per_frame == 0 {
            return Err(GpuError::Runtime(
                "the GPU pool, feedback buffer and upload budget must each hold at least one brick"
                    .into(),
            ));
        }
        // Check against the device before allocating anything of that size.
        let limit = ctx.limits.max_storage_buffer_binding_size;
        for (what, needed) in [
            ("brick grid", grid.pointers().len() as u64 * 4),
            ("brick masks", cfg.pool_slots as u64 * 64),
            ("brick metadata", cfg.pool_slots as u64 * 8),
            ("material arena", cfg.arena_bytes as u64),
            ("feedback", (cfg.feedback_capacity as u64 + 1) * 4),
        ] {
            if needed > limit {
                return Err(GpuError::TooLarge {
                    what,
                    needed,
                    limit,
                });
            }
        }
        let shadow: Vec<u32> = grid
            .pointers()
            .iter()
            .map(|&p| Self::unloaded_pointer(p, pool))
            .collect();
        let residency = Residency {
            mirror: BrickPool::default(),
            owner: FxHashMap::default(),
            slot_of: FxHashMap::default(),
            lod_of: FxHashMap::default(),
            last_seen: vec![0; cfg.pool_slots as usize],
            cfg,
        };
        Self::build(
            ctx,
            grid,
            palette,
            shadow,
            vec![0; cfg.pool_slots as usize * 16],
            vec![0; cfg.pool_slots as usize * 2],
            vec![0; (cfg.arena_bytes as usize).div_ceil(4)],
            cfg.pool_slots,
            Some(residency),
            cfg.feedback_capacity,
        )
    }

    /// The GPU pointer of a world grid pointer when nothing is resident.
    fn unloaded_pointer(p: u32, pool: &BrickPool) -> u32 {
        if p == 0 {
            0
        } else if p & UNIFORM != 0 {
            UNIFORM_GPU | (p & 0xff)
        } else {
            UNLOADED | pool.slot(p - 1).map_or(0, |b| lod565(b.lod_rgb()))
        }
    }

    #[allow(clippy::too_many_arguments)]
    fn build(
        ctx: &GpuContext,
        grid: &BrickGrid,
        palette: &Palette,
        shadow: Vec<u32>,
        masks: Vec<u32>,
        meta: Vec<u32>,
        arena: Vec<u32>,
        slots: u32,
        residency: Option<Residency>,
        feedback_capacity: u32,
    ) -> Result<Self, GpuError> {
        let dev = &ctx.device;
        let limit = ctx.limits.max_storage_buffer_binding_size;
        let pal: Vec<u32> = (0..=255u8)
            .map(|m| {
                let c = palette.rgb(m);
                c[0] as u32 | (c[1] as u32) << 8 | (c[2] as u32) << 16
            })
            .collect();
        let usage = wgpu::BufferUsages::STORAGE
            | wgpu::BufferUsages::COPY_DST
            | wgpu::BufferUsages::COPY_SRC;
        let make = |what: &'static str, v: &[u32]| -> Result<wgpu::Buffer, GpuError> {
            let needed = v.len() as u64 * 4;
            if needed > limit {
                return Err(GpuError::TooLarge {
                    what,
                    needed,
                    limit,
                });
            }
            let v: &[u32] = if v.is_empty() { &[0] } else { v };
            Ok(dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(what),
                contents: bytemuck::cast_slice(v),
                usage,
            }))
        };
        let grid_buf = make("brick grid", &shadow)?;
        let occ = make("occupancy layer", &occupancy_words(grid))?;
        let masks_buf = make("brick masks", &masks)?;
        let meta_buf = make("brick metadata", &meta)?;
        let arena_buf = make("material arena", &arena)?;
        let palette_buf = make("palette", &pal)?;
        let feedback = make("feedback", &vec![0; feedback_capacity as usize + 1])?;
        let last_seen = make("last seen", &vec![0; slots.max(1) as usize])?;
        let scope = dev.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = dev.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("brickmap.wgsl"),
            source: wgpu::ShaderSource::Wgsl(include_str!("brickmap.wgsl").into()),
        });
        let entry = |binding: u32, ty: wgpu::BufferBindingType| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        let ro = wgpu::BufferBindingType::Storage { read_only: true };
        let rw = wgpu::BufferBindingType::Storage { read_only: false };
        let entries = [
            entry(0, wgpu::BufferBindingType::Uniform),
            entry(1, rw),
            entry(2, ro),
            entry(3, ro),
            entry(4, ro),
            entry(5, ro),
            entry(6, ro),
            entry(7, rw),
            entry(8, rw),
            entry(9, rw),
        ];
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
            grid: grid_buf,
            occ,
            masks: masks_buf,
            meta: meta_buf,
            arena: arena_buf,
            palette: palette_buf,
            feedback,
            last_seen,
            shadow,
            residency,
            feedback_capacity,
            frame_no: 0,
            frame: Frame {
                anchor: grid.origin() << BRICK_SHIFT,
            },
            dims: grid.dims() << BRICK_SHIFT,
            slots,
        })
    }

    /// Bytes held on the GPU (pool and grid).
    pub fn gpu_bytes(&self) -> u64 {
        [
            &self.grid,
            &self.occ,
            &self.masks,
            &self.meta,
            &self.arena,
            &self.palette,
            &self.feedback,
            &self.last_seen,
        ]
        .iter()
        .map(|b| b.size())
        .sum()
    }

    /// Bytes of GPU memory in use: the grid and occupancy layer, plus the
    /// resident bricks (64-byte mask, 8-byte metadata, material block).
    pub fn gpu_bytes_used(&self) -> u64 {
        let fixed = self.grid.size() + self.occ.size() + self.palette.size();
        match &self.residency {
            Some(r) => {
                let arena: u64 = r
                    .owner
                    .keys()
                    .filter_map(|s| r.mirror.arena_block(*s))
                    .map(|(_, len)| len as u64)
                    .sum();
                fixed + r.mirror.len() as u64 * 72 + arena
            }
            None => self.gpu_bytes(),
        }
    }

    /// The grid pointers as the GPU holds them (see the shader for the
    /// encoding): for inspection and tests.
    pub fn pointers(&self) -> &[u32] {
        &self.shadow
    }

    /// Bricks currently resident (streaming) or uploaded (preloaded).
    pub fn resident(&self) -> u32 {
        self.residency
            .as_ref()
            .map_or(self.slots, |r| r.mirror.len() as u32)
    }

    fn set_pointer(&mut self, ctx: &GpuContext, i: u32, p: u32) {
        self.shadow[i as usize] = p;
        ctx.queue
            .write_buffer(&self.grid, i as u64 * 4, bytemuck::bytes_of(&p));
    }

    /// Render one frame; when streaming, then upload what rays asked for.
    /// `grid` and `pool` are the world's (the source of streamed bricks).
    pub fn render(
        &mut self,
        ctx: &GpuContext,
        camera: &Camera,
        opts: &RenderOptions,
        grid: &BrickGrid,
        pool: &BrickPool,
    ) -> Result<(GpuFrame, FrameStats), GpuError> {
        self.frame_no += 1;
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
            frame: self.frame_no,
            feedback_capacity: self.feedback_capacity,
            _pad: [0; 3],
        };
        ctx.queue
            .write_buffer(&self.feedback, 0, bytemuck::bytes_of(&0u32));
        let pixels = (w * h) as u64;
        let out_size = pixels * std::mem::size_of::<PixelOut>() as u64;
        let fb_size = self.feedback.size();
        let ls_size = self.last_seen.size();
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
            size: out_size + fb_size + ls_size,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let buffers = [
            &uniform,
            &self.grid,
            &self.occ,
            &self.masks,
            &self.meta,
            &self.arena,
            &self.palette,
            &out,
            &self.feedback,
            &self.last_seen,
        ];
        let entries: Vec<wgpu::BindGroupEntry> = buffers
            .iter()
            .enumerate()
            .map(|(i, b)| wgpu::BindGroupEntry {
                binding: i as u32,
                resource: b.as_entire_binding(),
            })
            .collect();
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
        enc.copy_buffer_to_buffer(&self.feedback, 0, &staging, out_size, fb_size);
        enc.copy_buffer_to_buffer(&self.last_seen, 0, &staging, out_size + fb_size, ls_size);
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
        let px: &[PixelOut] = bytemuck::cast_slice(&data[..out_size as usize]);
        let fb: &[u32] =
            bytemuck::cast_slice(&data[out_size as usize..(out_size + fb_size) as usize]);
        let ls: &[u32] = bytemuck::cast_slice(&data[(out_size + fb_size) as usize..]);
        let mut frame = GpuFrame {
            width: w,
            height: h,
            rgb: Vec::with_capacity(pixels as usize * 3),
            depth: Vec::with_capacity(pixels as usize),
            hits: Vec::with_capacity(pixels as usize),
            lod_pixels: 0,
            lod: Vec::with_capacity(pixels as usize),
        };
        for p in px {
            frame.lod.push(p.normal & 8 != 0);
            frame
                .rgb
                .extend_from_slice(&[p.rgba as u8, (p.rgba >> 8) as u8, (p.rgba >> 16) as u8]);
            if p.normal == 0 {
                frame.depth.push(f32::INFINITY);
                frame.hits.push(None);
            } else {
                let code = p.normal & 7;
                frame.lod_pixels += (p.normal & 8 != 0) as u32;
                frame.depth.push(p.depth);
                let mut n = IVec3::ZERO;
                if code != 7 {
                    let axis = ((code - 1) / 2) as usize;
                    n[axis] = if (code - 1) % 2 == 1 { 1 } else { -1 };
                }
                frame.hits.push(Some((IVec3::new(p.vx, p.vy, p.vz), n)));
            }
        }
        let count = fb[0];
        let requests: Vec<u32> = fb[1..1 + (count.min(self.feedback_capacity) as usize)].to_vec();
        if let Some(res) = self.residency.as_mut() {
            let n = res.last_seen.len();
            res.last_seen.copy_from_slice(&ls[..n]);
        }
        drop(data);
        staging.unmap();
        let mut stats = FrameStats {
            requests: requests.len() as u32,
            overflowed: count.saturating_sub(self.feedback_capacity),
            ..Default::default()
        };
        if self.residency.is_some() {
            for &i in &requests {
                let p = self.shadow[i as usize];
                self.shadow[i as usize] = (p & !STATE_MASK) | REQUESTED;
            }
            self.serve(ctx, &requests, grid, pool, &mut stats)?;
            stats.resident = self.resident();
        } else {
            stats.resident = self.slots;
        }
        Ok((frame, stats))
    }

    /// Upload up to the per-frame budget of requested bricks; put the rest
    /// back to unloaded so that rays ask again.
    fn serve(
        &mut self,
        ctx: &GpuContext,
        requests: &[u32],
        grid: &BrickGrid,
        pool: &BrickPool,
        stats: &mut FrameStats,
    ) -> Result<(), GpuError> {
        let budget = self
            .residency
            .as_ref()
            .map_or(0, |r| r.cfg.uploads_per_frame) as usize;
        let dims = grid.dims();
        let mut dense = [0u8; BRICK_VOXELS];
        for (k, &i) in requests.iter().enumerate() {
            let p = self.shadow[i as usize];
            let unloaded = (p & !STATE_MASK) | UNLOADED;
            if k >= budget {
                self.set_pointer(ctx, i, unloaded);
                continue;
            }
            let l = IVec3::new(
                i as i32 % dims.x,
                (i as i32 / dims.x) % dims.y,
                i as i32 / (dims.x * dims.y),
            );
            let wp = grid.pointer(l);
            let Some(brick) = (wp != 0 && wp & UNIFORM == 0)
                .then(|| pool.slot(wp - 1))
                .flatten()
            else {
                // The world changed under the request: re-encode the pointer.
                let np = Self::unloaded_pointer(wp, pool);
                self.set_pointer(ctx, i, np);
                continue;
            };
            brick.to_dense(&mut dense);
            let lod = lod565(brick.lod_rgb());
            if let BrickContent::Mixed(full) =
                BrickContent::from_dense(&dense, &Palette::grey_ramp())
            {
                stats.unculled_material_bytes += material_bytes(&full);
            }
            cull_hidden_materials(&mut dense);
            let BrickContent::Mixed(b) = BrickContent::from_dense(&dense, &Palette::grey_ramp())
            else {
                continue;
            };
            stats.material_bytes += material_bytes(&b);
            if let Some(res) = self.residency.as_mut() {
                res.lod_of.insert(i, lod);
            }
            let Some(slot) = self.admit(ctx, i, b, stats)? else {
                if let Some(res) = self.residency.as_mut() {
                    res.lod_of.remove(&i);
                }
                self.set_pointer(ctx, i, unloaded);
                continue;
            };
            self.set_pointer(ctx, i, slot + 1);
        }
        Ok(())
    }

    /// Put a brick into the pool (evicting least recently seen bricks if
    /// needed) and upload it. `None` if nothing could be evicted.
    fn admit(
        &mut self,
        ctx: &GpuContext,
        index: u32,
        brick: crate::world::Brick,
        stats: &mut FrameStats,
    ) -> Result<Option<u32>, GpuError> {
        for _attempt in 0..2 {
            let frame_no = self.frame_no;
            let res = self.residency.as_mut().expect("streaming");
            let full = res.mirror.len() as u32 >= res.cfg.pool_slots;
            if !full {
                let id = res.mirror.insert(brick.clone());
                let cap = res.cfg.arena_bytes as usize;
                let fits = id.index() < res.cfg.pool_slots
                    && res
                        .mirror
                        .arena_block(id.index())
                        .is_none_or(|(off, len)| off + len <= cap);
                if fits {
                    let slot = id.index();
                    res.owner.insert(slot, index);
                    res.slot_of.insert(index, id);
                    let (masks, meta, arena) = res.mirror.raw();
                    let mask_words: Vec<u32> = masks[slot as usize]
                        .iter()
                        .flat_map(|w| [*w as u32, (*w >> 32) as u32])
                        .collect();
                    ctx.queue.write_buffer(
                        &self.masks,
                        slot as u64 * 64,
                        bytemuck::cast_slice(&mask_words),
                    );
                    ctx.queue.write_buffer(
                        &self.meta,
                        slot as u64 * 8,
                        bytemuck::cast_slice(&meta[slot as usize]),
                    );
                    stats.upload_bytes += 72;
                    if let Some((off, len)) = res.mirror.arena_block(slot) {
                        // Arena writes must be 4-byte aligned: blocks are 16-byte aligned.
                        ctx.queue
                            .write_buffer(&self.arena, off as u64, &arena[off..off + len]);
                        stats.upload_bytes += len as u64;
                    }
                    stats.uploads += 1;
                    return Ok(Some(slot));
                }
                res.mirror.remove(id);
            }
            // Evict the least recently seen resident brick not seen this frame.
            let victim = res
                .owner
                .iter()
                .filter(|(slot, _)| res.last_seen[**slot as usize] < frame_no)
                .min_by_key(|(slot, _)| (res.last_seen[**slot as usize], **slot))
                .map(|(s, i)| (*s, *i));
            let Some((_, victim_index)) = victim else {
                return Ok(None);
            };
            self.evict(ctx, victim_index);
            stats.evictions += 1;
        }
        Ok(None)
    }

    /// Drop grid index `i`'s brick from the pool; its pointer becomes unloaded.
    fn evict(&mut self, ctx: &GpuContext, i: u32) {
        let Some(res) = self.residency.as_mut() else {
            return;
        };
        if let Some(id) = res.slot_of.remove(&i) {
            let lod = res.lod_of.remove(&i).unwrap_or(0);
            res.owner.remove(&id.index());
            res.mirror.remove(id);
            self.set_pointer(ctx, i, UNLOADED | lod);
        }
    }

    /// Apply the world's edits to bricks `changed` (world brick coordinates,
    /// duplicates allowed): pointers go back to unloaded with their new LOD
    /// colour (or empty / uniform), freed slots return to the pool, and the
    /// occupancy layer is refreshed. Only meaningful when streaming.
    pub fn apply_edits(
        &mut self,
        ctx: &GpuContext,
        grid: &BrickGrid,
        pool: &BrickPool,
        changed: &[IVec3],
    ) {
        let dims = grid.dims();
        let mut seen = rustc_hash::FxHashSet::default();
        for &b in changed {
            let l = b - grid.origin();
            if l.cmplt(IVec3::ZERO).any() || l.cmpge(dims).any() || !seen.insert(l) {
                continue;
            }
            let i = (l.x + dims.x * (l.y + dims.y * l.z)) as u32;
            if let Some(res) = self.residency.as_mut()
                && let Some(id) = res.slot_of.remove(&i)
            {
                res.lod_of.remove(&i);
                res.owner.remove(&id.index());
                res.mirror.remove(id);
            }
            let p = Self::unloaded_pointer(grid.pointer(l), pool);
            self.set_pointer(ctx, i, p);
        }
        ctx.queue
            .write_buffer(&self.occ, 0, bytemuck::cast_slice(&occupancy_words(grid)));
    }
}
