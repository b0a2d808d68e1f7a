//! The GPU brickmap: its buffers and compute pipelines. One frame's dispatch
//! and readback live in [`super::frame`]; pool residency (what is uploaded,
//! evicted, invalidated) in [`super::stream`].
//!
//! Two ways to fill the pool:
//! - [`GpuBrickmap::preloaded`]: every brick uploaded up front (still images,
//!   parity tests);
//! - [`GpuBrickmap::streaming`]: every mixed brick starts *unloaded*; rays that
//!   reach one shade it with its LOD colour and request it; after each frame at
//!   most `uploads_per_frame` requested bricks are uploaded into free slots,
//!   evicting the least recently seen bricks when the pool is full.

use glam::IVec3;
use rustc_hash::FxHashMap;
use wgpu::util::DeviceExt;

use super::stream::{Residency, StreamConfig};
use super::{GpuContext, GpuError};
use crate::trace::Frame;
use crate::world::{BRICK_SHIFT, BrickGrid, BrickPool, BrickRef, GPU_META_WORDS, Palette, UNIFORM};

pub(super) const UNLOADED: u32 = 0x4000_0000;
pub(super) const REQUESTED: u32 = 0x8000_0000;
const UNIFORM_GPU: u32 = 0xC000_0000;
pub(super) const STATE_MASK: u32 = 0xC000_0000;

/// The brickmap on the GPU.
pub struct GpuBrickmap {
    pub(super) pipeline: wgpu::ComputePipeline,
    /// The coarse pass of beam starts (entry point `beam_pass`).
    pub(super) beam_pipeline: wgpu::ComputePipeline,
    pub(super) layout: wgpu::BindGroupLayout,
    pub(super) grid: wgpu::Buffer,
    pub(super) coarse: wgpu::Buffer,
    pub(super) masks: wgpu::Buffer,
    pub(super) meta: wgpu::Buffer,
    pub(super) arena: wgpu::Buffer,
    pub(super) palette: wgpu::Buffer,
    pub(super) feedback: wgpu::Buffer,
    pub(super) last_seen: wgpu::Buffer,
    /// CPU copy of the grid pointers as the GPU holds them.
    pub(super) shadow: Vec<u32>,
    pub(super) residency: Option<Residency>,
    pub(super) feedback_capacity: u32,
    pub(super) frame_no: u32,
    pub(super) frame: Frame,
    pub(super) dims: IVec3,
    pub(super) slots: u32,
    /// Timestamp queries and their resolve buffer, made at the first frame
    /// on a device that has them.
    pub(super) timer: Option<(wgpu::QuerySet, wgpu::Buffer)>,
}

/// The palette as the shader reads it: one `0x00BBGGRR` word per material.
fn palette_words(palette: &Palette) -> Vec<u32> {
    (0..=255u8)
        .map(|m| {
            let c = palette.rgb(m);
            c[0] as u32 | (c[1] as u32) << 8 | (c[2] as u32) << 16
        })
        .collect()
}

/// What the GPU's brick buffers start with: the grid's GPU pointers
/// (`shadow`), the pool's masks, metadata and material arena as words, and
/// how many slots the pool has.
struct Contents {
    shadow: Vec<u32>,
    masks: Vec<u32>,
    meta: Vec<u32>,
    arena: Vec<u32>,
    slots: u32,
}

impl GpuBrickmap {
    /// Upload `palette` (a hot reload of `materials.lua` recolours
    /// materials; the bricks' LOD colours come with their edits).
    pub fn set_palette(&self, ctx: &GpuContext, palette: &Palette) {
        ctx.queue.write_buffer(
            &self.palette,
            0,
            bytemuck::cast_slice(&palette_words(palette)),
        );
    }
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

pub(super) fn lod565(c: [u8; 3]) -> u32 {
    ((c[0] as u32 >> 3) << 11) | ((c[1] as u32 >> 2) << 5) | (c[2] as u32 >> 3)
}

/// Bytes of metadata per pool slot on the GPU.
pub(super) const META_BYTES: u64 = 4 * GPU_META_WORDS as u64;

/// The low bits of an unloaded pointer: the brick's material (what a
/// coarse hit reports) in bits 16..24 and its average colour as RGB565 (what
/// a ray shows while the brick is on its way).
pub(super) fn unloaded_bits(b: &BrickRef<'_>) -> u32 {
    (b.lod().whole as u32) << 16 | lod565(b.lod_rgb())
}

/// The grid's levels 5 then 4 (material bytes, 0 when empty) as words, and
/// the word offset of level 4.
pub(super) fn coarse_words(grid: &BrickGrid) -> Vec<u32> {
    let (l4, l5) = grid.coarse().raw();
    let mut w = words_of(l5);
    w.extend(words_of(l4));
    w
}

pub(super) fn l4_offset(grid: &BrickGrid) -> u32 {
    grid.coarse().raw().1.len().div_ceil(4) as u32
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
        let contents = Contents {
            shadow,
            masks: mask_words,
            meta: meta_words,
            arena: words_of(arena),
            slots: masks.len() as u32,
        };
        Self::build(ctx, grid, palette, contents, None, 1)
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
        // Check against the device before allocating anything of that size:
        // a pool too large for it shrinks (with the figures), the rest must
        // fit.
        let limit = ctx.limits.max_storage_buffer_binding_size;
        let (cfg, warning) = super::stream::fit_pool(cfg, limit);
        if let Some(w) = warning {
            crate::say!("warning: {w}");
        }
        for (what, needed) in [
            ("brick grid", grid.pointers().len() as u64 * 4),
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
        let contents = Contents {
            shadow,
            masks: vec![0; cfg.pool_slots as usize * 16],
            meta: vec![0; cfg.pool_slots as usize * GPU_META_WORDS],
            arena: vec![0; (cfg.arena_bytes as usize).div_ceil(4)],
            slots: cfg.pool_slots,
        };
        Self::build(
            ctx,
            grid,
            palette,
            contents,
            Some(residency),
            cfg.feedback_capacity,
        )
    }

    /// The GPU pointer of a world grid pointer when nothing is resident.
    pub(super) fn unloaded_pointer(p: u32, pool: &BrickPool) -> u32 {
        if p == 0 {
            0
        } else if p & UNIFORM != 0 {
            UNIFORM_GPU | (p & 0xff)
        } else {
            UNLOADED | pool.slot(p - 1).map_or(0, |b| unloaded_bits(&b))
        }
    }

    fn build(
        ctx: &GpuContext,
        grid: &BrickGrid,
        palette: &Palette,
        contents: Contents,
        residency: Option<Residency>,
        feedback_capacity: u32,
    ) -> Result<Self, GpuError> {
        let Contents {
            shadow,
            masks,
            meta,
            arena,
            slots,
        } = contents;
        let dev = &ctx.device;
        let limit = ctx.limits.max_storage_buffer_binding_size;
        let pal = palette_words(palette);
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
        let coarse = make("coarse levels", &coarse_words(grid))?;
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
            entry(10, rw),
            entry(11, rw),
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
        let beam_pipeline = dev.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("beam starts"),
            layout: Some(&pl),
            module: &module,
            entry_point: Some("beam_pass"),
            compilation_options: Default::default(),
            cache: None,
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Shader(e.to_string()));
        }
        Ok(GpuBrickmap {
            pipeline,
            beam_pipeline,
            layout,
            grid: grid_buf,
            coarse,
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
            timer: None,
        })
    }

    /// Bytes held on the GPU (pool and grid).
    pub fn gpu_bytes(&self) -> u64 {
        [
            &self.grid,
            &self.coarse,
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

    /// Bytes of GPU memory in use: the grid and its coarse levels, plus the
    /// resident bricks (64-byte mask, 16-byte metadata, material block).
    pub fn gpu_bytes_used(&self) -> u64 {
        match &self.residency {
            Some(r) => self.bytes_with(r, |_| true).0,
            None => self.gpu_bytes(),
        }
    }

    /// The grid and its coarse levels, plus the resident bricks whose slot
    /// `keep` takes (64-byte mask, metadata, material block); and how
    /// many bricks that is.
    fn bytes_with(&self, r: &super::stream::Residency, keep: impl Fn(u32) -> bool) -> (u64, u32) {
        let fixed = self.grid.size() + self.coarse.size() + self.palette.size();
        let (mut bytes, mut n) = (fixed, 0u32);
        for &s in r.owner.keys().filter(|&&s| keep(s)) {
            let arena = r.mirror.arena_block(s).map_or(0, |(_, len)| len as u64);
            bytes += 64 + META_BYTES + arena;
            n += 1;
        }
        (bytes, n)
    }

    /// Of [`gpu_bytes_used`](Self::gpu_bytes_used), the bytes of the bricks
    /// the last frame's rays touched (its working set), with the grid,
    /// and how many bricks that is. Bricks uploaded after that frame carry
    /// its stamp too, so this is the working set only after a frame that
    /// asked for nothing (as `bench stream` takes it). `None` unless
    /// streaming.
    pub fn working_set(&self) -> Option<(u64, u32)> {
        let r = self.residency.as_ref()?;
        Some(self.bytes_with(r, |s| r.last_seen[s as usize] == self.frame_no))
    }

    /// The grid pointers as the GPU holds them (see the shader for the
    /// encoding): for inspection and tests.
    pub fn pointers(&self) -> &[u32] {
        &self.shadow
    }

    /// Brick slots in the pool (it grows when a view needs more).
    pub fn pool_slots(&self) -> u32 {
        self.slots
    }

    /// Bricks currently resident (streaming) or uploaded (preloaded).
    pub fn resident(&self) -> u32 {
        self.residency
            .as_ref()
            .map_or(self.slots, |r| r.mirror.len() as u32)
    }

    pub(super) fn set_pointer(&mut self, ctx: &GpuContext, i: u32, p: u32) {
        self.shadow[i as usize] = p;
        ctx.queue
            .write_buffer(&self.grid, i as u64 * 4, bytemuck::bytes_of(&p));
    }
}
