//! One GPU frame: the parameters block, the dispatch of the beam pass and
//! the tracer, the readback of pixels and feedback, and (when streaming)
//! the uploads the frame's rays asked for.

use bytemuck::{Pod, Zeroable};
use glam::{DVec3, IVec3};
use wgpu::util::DeviceExt;

use super::stream::FrameStats;
use super::tracer::{GpuBrickmap, REQUESTED, STATE_MASK, UNLOADED, l4_offset};
use super::{GpuContext, GpuError, GpuFrame};
use crate::trace::{Camera, Frame, RenderOptions};
use crate::world::{BRICK_SHIFT, BrickGrid, BrickPool};

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
    pub(super) dims: [i32; 3],
    height: u32,
    anchor: [i32; 3],
    pub(super) frame: u32,
    pub(super) feedback_capacity: u32,
    /// The grid's ring (physical cell of local brick 0), for toroidal
    /// addressing of a sliding grid.
    ring: [i32; 3],
    /// Distance fog extent in voxels (0: none).
    fog: f32,
    /// Level of detail: `C ·` pixel angle (0: exact).
    lod_k: f32,
    /// Word offset of level 4 in the coarse buffer (level 5 is first).
    l4_offset: u32,
    /// Ambient occlusion on (1) or off (0).
    ao: u32,
    /// Where primary rays pass in each pixel (0.5, 0.5: the centre).
    jitter: [f32; 2],
    /// Beam starts on (1) or off (0).
    beam: u32,
    /// Colour alone, one word per pixel into the image buffer (1), or
    /// every output into the pixel buffer (0).
    image_only: u32,
}

/// Bytes a pixel's outputs take on the device and in a `render` readback.
pub(super) const PIXEL_BYTES: u64 = std::mem::size_of::<PixelOut>() as u64;

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

impl GpuBrickmap {
    /// Start a frame of `camera`: its number and anchor, its parameters,
    /// the feedback count reset, its output and beam buffers and the bind
    /// group over them and the brick buffers; returns the bind group and
    /// the output buffer to read back: every output per pixel, or with
    /// `image_only` its colour alone (4 bytes a pixel instead of 24).
    fn frame_bindings(
        &mut self,
        ctx: &GpuContext,
        camera: &Camera,
        opts: &RenderOptions,
        grid: &BrickGrid,
        image_only: bool,
    ) -> Result<(wgpu::BindGroup, wgpu::Buffer), GpuError> {
        let dev = &ctx.device;
        self.frame_no += 1;
        // A sliding grid moves its origin; its buffers are addressed
        // physically, through the ring.
        self.frame = Frame {
            anchor: grid.origin() << BRICK_SHIFT,
        };
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
            ring: grid.ring().to_array(),
            fog: opts.fog,
            lod_k: opts.lod * camera.pixel_angle() as f32,
            l4_offset: l4_offset(grid),
            ao: opts.ao as u32,
            jitter: opts.jitter.unwrap_or([0.5, 0.5]).map(|v| v as f32),
            beam: opts.beam as u32,
            image_only: image_only as u32,
        };
        ctx.queue
            .write_buffer(&self.feedback, 0, bytemuck::bytes_of(&0u32));
        let pixels = w as u64 * h as u64;
        let px_size = std::mem::size_of::<PixelOut>() as u64;
        let out_size = if image_only {
            px_size
        } else {
            pixels * px_size
        };
        let image_size = if image_only { pixels * 4 } else { 4 };
        // Checked before any buffer exists: past the binding limit wgpu
        // fails validation with a panic (regression: 3840×2160 on lavapipe).
        ctx.check_frame_bytes(w, h, out_size.max(image_size))?;
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
        let image = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("image"),
            size: image_size,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        // Timestamps: [0] the first pass's start, [1] the trace's end,
        // [2] the beam pass's end.
        if ctx.timestamps && self.timer.is_none() {
            let set = dev.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("tracer time"),
                ty: wgpu::QueryType::Timestamp,
                count: 3,
            });
            let resolve = dev.create_buffer(&wgpu::BufferDescriptor {
                label: Some("tracer time"),
                size: 3 * 8,
                usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            });
            self.timer = Some((set, resolve));
        }
        let (bw, bh) = (w.div_ceil(8), h.div_ceil(8));
        let beams = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("beam starts"),
            size: (bw * bh) as u64 * 4,
            usage: wgpu::BufferUsages::STORAGE,
            mapped_at_creation: false,
        });
        let buffers = [
            &uniform,
            &self.grid,
            &self.coarse,
            &self.masks,
            &self.meta,
            &self.arena,
            &self.palette,
            &out,
            &self.feedback,
            &self.last_seen,
            &beams,
            &image,
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
        Ok((bind, if image_only { image } else { out }))
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
        let (w, h) = (camera.width, camera.height);
        self.run_frame(ctx, camera, opts, (grid, pool), false, |bytes| {
            decode_pixels(bytemuck::cast_slice(bytes), w, h)
        })
    }

    /// Render one frame's image alone (row-major RGB8), reading back 4
    /// bytes a pixel instead of [`render`](Self::render)'s 24 and decoding
    /// nothing else; streaming goes on as with `render`. For frames that
    /// are only shown (the daemon's): on an H200 at 1920×1080 a whole
    /// `render` cost 43 to 72 ms, nearly all of it reading back and
    /// decoding, for 1.2 to 2.9 ms of tracing; `render_image` 3.8 to 6.3.
    pub fn render_image(
        &mut self,
        ctx: &GpuContext,
        camera: &Camera,
        opts: &RenderOptions,
        grid: &BrickGrid,
        pool: &BrickPool,
    ) -> Result<(Vec<u8>, FrameStats), GpuError> {
        self.run_frame(ctx, camera, opts, (grid, pool), true, |bytes| {
            let words: &[u32] = bytemuck::cast_slice(bytes);
            let mut rgb = vec![0u8; words.len() * 3];
            for (px, &c) in rgb.chunks_exact_mut(3).zip(words) {
                px.copy_from_slice(&rgb_of(c));
            }
            rgb
        })
    }

    /// One frame: bind, trace, read back the outputs (`decode` turns
    /// their bytes into the result), the feedback, the last-seen stamps
    /// and the timestamps; then serve what rays asked for.
    fn run_frame<T>(
        &mut self,
        ctx: &GpuContext,
        camera: &Camera,
        opts: &RenderOptions,
        (grid, pool): (&BrickGrid, &BrickPool),
        image_only: bool,
        decode: impl FnOnce(&[u8]) -> T,
    ) -> Result<(T, FrameStats), GpuError> {
        let dev = &ctx.device;
        let (w, h) = (camera.width, camera.height);
        let (bind, out) = self.frame_bindings(ctx, camera, opts, grid, image_only)?;
        let out_size = out.size();
        let fb_size = self.feedback.size();
        let ls_size = self.last_seen.size();
        let ts_size = if self.timer.is_some() { 3 * 8 } else { 0 };
        let staging = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size: out_size + fb_size + ls_size + ts_size,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut enc = dev.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("frame"),
        });
        self.encode_passes(&mut enc, &bind, opts, (w, h), (true, true));
        enc.copy_buffer_to_buffer(&out, 0, &staging, 0, out_size);
        enc.copy_buffer_to_buffer(&self.feedback, 0, &staging, out_size, fb_size);
        enc.copy_buffer_to_buffer(&self.last_seen, 0, &staging, out_size + fb_size, ls_size);
        let queries = if opts.beam { 3 } else { 2 };
        if let Some((set, resolve)) = &self.timer {
            enc.resolve_query_set(set, 0..queries, resolve, 0);
            enc.copy_buffer_to_buffer(
                resolve,
                0,
                &staging,
                out_size + fb_size + ls_size,
                queries as u64 * 8,
            );
        }
        ctx.queue.submit([enc.finish()]);
        let slice = staging.slice(..);
        let data = map_read(dev, &slice)?;
        let fb: &[u32] =
            bytemuck::cast_slice(&data[out_size as usize..(out_size + fb_size) as usize]);
        let ls_end = (out_size + fb_size + ls_size) as usize;
        let ls: &[u32] = bytemuck::cast_slice(&data[(out_size + fb_size) as usize..ls_end]);
        // Ticks to ms; read unaligned (the staging offset is only 4-aligned).
        let period_ms = ctx.queue.get_timestamp_period() as f64 * 1e-6;
        let tick = |i: usize| {
            let b = &data[ls_end + i * 8..ls_end + i * 8 + 8];
            u64::from_le_bytes(b.try_into().unwrap_or([0; 8]))
        };
        let span = |a: usize, b: usize| tick(b).saturating_sub(tick(a)) as f64 * period_ms;
        let gpu_ms = self.timer.is_some().then(|| span(0, 1));
        let beam_ms = (self.timer.is_some() && opts.beam).then(|| span(0, 2));
        let frame = decode(&data[..out_size as usize]);
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
            gpu_ms,
            beam_ms,
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

    /// The beam-start pass (with beams on) and the trace of one frame into
    /// `enc`. With timestamps, `first` writes the start of the frame's
    /// first pass into query 0 and `last` the trace's end into query 1
    /// (and, when both, the beam pass's end into query 2), so that several
    /// frames encoded back to back are timed as one span.
    fn encode_passes(
        &self,
        enc: &mut wgpu::CommandEncoder,
        bind: &wgpu::BindGroup,
        opts: &RenderOptions,
        (w, h): (u32, u32),
        (first, last): (bool, bool),
    ) {
        let (bw, bh) = (w.div_ceil(8), h.div_ceil(8));
        if opts.beam {
            // Its own pass, so that its writes are visible to the next.
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("beam starts"),
                timestamp_writes: self.timer.as_ref().filter(|_| first).map(|(set, _)| {
                    wgpu::ComputePassTimestampWrites {
                        query_set: set,
                        beginning_of_pass_write_index: Some(0),
                        end_of_pass_write_index: last.then_some(2),
                    }
                }),
            });
            pass.set_pipeline(&self.beam_pipeline);
            pass.set_bind_group(0, bind, &[]);
            pass.dispatch_workgroups(bw.div_ceil(8), bh.div_ceil(8), 1);
        }
        let begin = (first && !opts.beam).then_some(0);
        let end = last.then_some(1);
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("trace"),
            timestamp_writes: self
                .timer
                .as_ref()
                .filter(|_| begin.is_some() || end.is_some())
                .map(|(set, _)| wgpu::ComputePassTimestampWrites {
                    query_set: set,
                    beginning_of_pass_write_index: begin,
                    end_of_pass_write_index: end,
                }),
        });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, bind, &[]);
        pass.dispatch_workgroups(w.div_ceil(8), h.div_ceil(8), 1);
    }

    /// The tracer's device time per frame, ms, over `repeats` frames of
    /// `camera` traced back to back in one submission with nothing read
    /// back between them (so that the device stays busy and at its working
    /// clocks); `None` where the device has no timestamps. For benchmarks:
    /// on a view not yet converged it times frames that show some bricks
    /// by their LOD colour; the bricks its rays claimed are put back to
    /// unloaded, so that the next [`render`](Self::render) asks for them.
    pub fn sustained_ms(
        &mut self,
        ctx: &GpuContext,
        camera: &Camera,
        opts: &RenderOptions,
        grid: &BrickGrid,
        repeats: u32,
    ) -> Result<Option<f64>, GpuError> {
        if !ctx.timestamps {
            return Ok(None);
        }
        let (w, h) = (camera.width, camera.height);
        let (bind, _out) = self.frame_bindings(ctx, camera, opts, grid, false)?;
        let Some((set, resolve)) = &self.timer else {
            return Ok(None);
        };
        let dev = &ctx.device;
        let mut enc = dev.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("sustained"),
        });
        let repeats = repeats.max(1);
        for i in 0..repeats {
            self.encode_passes(&mut enc, &bind, opts, (w, h), (i == 0, i + 1 == repeats));
        }
        // The feedback too: rays that met unloaded bricks claimed them, and
        // the claims are undone below so that the next frame asks again.
        let fb_size = self.feedback.size();
        let staging = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("tracer time"),
            size: 16 + fb_size,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        enc.resolve_query_set(set, 0..2, resolve, 0);
        enc.copy_buffer_to_buffer(resolve, 0, &staging, 0, 16);
        enc.copy_buffer_to_buffer(&self.feedback, 0, &staging, 16, fb_size);
        ctx.queue.submit([enc.finish()]);
        let slice = staging.slice(..);
        let data = map_read(dev, &slice)?;
        let t: &[u64] = bytemuck::cast_slice(&data[..16]);
        let ticks = t[1].saturating_sub(t[0]) as f64;
        let fb: &[u32] = bytemuck::cast_slice(&data[16..]);
        let claimed: Vec<u32> = fb[1..1 + (fb[0].min(self.feedback_capacity) as usize)].to_vec();
        drop(data);
        staging.unmap();
        // Regression (hostile review): claims left in place stayed
        // "requested" on the device with nobody to serve them, so a view
        // timed before it had converged never converged. The shadow still
        // holds each claimed brick's unloaded pointer.
        for i in claimed {
            let p = self.shadow[i as usize];
            self.set_pointer(ctx, i, (p & !STATE_MASK) | UNLOADED);
        }
        Ok(Some(
            ticks * ctx.queue.get_timestamp_period() as f64 * 1e-6 / repeats as f64,
        ))
    }
}

/// Map `slice` for reading, waiting for the device.
pub(super) fn map_read<'a>(
    dev: &wgpu::Device,
    slice: &wgpu::BufferSlice<'a>,
) -> Result<wgpu::BufferView, GpuError> {
    let (tx, rx) = std::sync::mpsc::channel();
    slice.map_async(wgpu::MapMode::Read, move |r| {
        let _ = tx.send(r);
    });
    dev.poll(wgpu::PollType::wait_indefinitely())
        .map_err(|e| GpuError::Runtime(e.to_string()))?;
    rx.recv()
        .map_err(|e| GpuError::Runtime(e.to_string()))?
        .map_err(|e| GpuError::Runtime(e.to_string()))?;
    slice
        .get_mapped_range()
        .map_err(|e| GpuError::Runtime(e.to_string()))
}

/// Every output of a frame's pixels, as [`GpuFrame`] holds them.
fn decode_pixels(px: &[PixelOut], w: u32, h: u32) -> GpuFrame {
    let pixels = px.len();
    let mut frame = GpuFrame {
        width: w,
        height: h,
        rgb: Vec::with_capacity(pixels * 3),
        depth: Vec::with_capacity(pixels),
        hits: Vec::with_capacity(pixels),
        lod_pixels: 0,
        lod: Vec::with_capacity(pixels),
    };
    for p in px {
        frame.lod.push(p.normal & 8 != 0);
        frame.rgb.extend_from_slice(&rgb_of(p.rgba));
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
    frame
}

/// A pixel's colour word (`0xAABBGGRR`, as the shader packs it) as RGB8.
fn rgb_of(word: u32) -> [u8; 3] {
    let [r, g, b, _] = word.to_le_bytes();
    [r, g, b]
}
