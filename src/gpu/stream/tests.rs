//! Tests of the GPU pool's streaming: pool fitting, stamps, arena
//! compaction and eviction, and small-buffer devices.

use super::*;

/// A pool too large for the device shrinks to fit, with the figures;
/// one that fits is left alone.
#[test]
fn a_pool_too_large_for_the_device_shrinks_with_a_warning() {
    let asked = StreamConfig {
        pool_slots: 1 << 24,
        arena_bytes: u32::MAX,
        ..StreamConfig::default()
    };
    let (cfg, warning) = fit_pool(asked, 128 << 20);
    assert_eq!(cfg.pool_slots, (128 << 20) / 64);
    assert_eq!(cfg.arena_bytes, 128 << 20);
    let w = warning.expect("a warning");
    assert!(
        w.contains("134217728 bytes") && w.contains("2097152 slots") && w.contains("16777216"),
        "{w}"
    );
    let (same, none) = fit_pool(StreamConfig::default(), 1 << 30);
    assert_eq!(same, StreamConfig::default());
    assert!(none.is_none());
}

/// A small terrain world, 64×32×64.
fn terrain() -> crate::scene::SceneWorld {
    crate::scene::build_scene(
        &crate::scene::SceneSpec::Terrain { caves: false },
        IVec3::new(64, 32, 64),
        3,
        &indicatif::ProgressBar::hidden(),
    )
    .unwrap()
}

/// A streaming pool of 256 slots (its cap) and a 16 KiB arena.
fn small_arena_pool(ctx: &GpuContext, w: &crate::scene::SceneWorld) -> GpuBrickmap {
    let cfg = StreamConfig {
        pool_slots: 256,
        arena_bytes: 16384,
        max_pool_slots: 256,
        ..StreamConfig::default()
    };
    GpuBrickmap::streaming(ctx, w.grid(), w.store().pool(), w.store().palette(), cfg).unwrap()
}

/// A full brick of `k` materials (its arena block grows with `k`),
/// shifted by `salt`.
fn brick(k: usize, salt: usize) -> crate::world::Brick {
    let d: [u8; BRICK_VOXELS] = std::array::from_fn(|i| 1 + ((i + salt) % k) as u8);
    match BrickContent::from_dense(&d, &Palette::grey_ramp()) {
        BrickContent::Mixed(b) => b,
        _ => unreachable!("a full brick of several materials is mixed"),
    }
}

/// In frame `frame`, admit a brick of `k` materials for each grid
/// index of `indices`, requiring each to be admitted.
fn admit_all(
    ctx: &GpuContext,
    g: &mut GpuBrickmap,
    (frame, indices, k): (u32, std::ops::Range<u32>, usize),
    stats: &mut FrameStats,
) {
    g.frame_no = frame;
    for i in indices {
        let slot = g.admit(ctx, i, brick(k, i as usize), stats).unwrap();
        assert!(slot.is_some(), "brick {i} not admitted: {stats:?}");
    }
}

/// A GPU context, or `None` (a skip, unless `BRICKWORLD_REQUIRE_GPU=1`).
fn context() -> Option<GpuContext> {
    match GpuContext::new() {
        Ok(c) => Some(c),
        Err(e) if std::env::var("BRICKWORLD_REQUIRE_GPU").as_deref() == Ok("1") => {
            panic!("GPU required but unavailable: {e}")
        }
        Err(e) => {
            crate::say!("{e}: skipping (set BRICKWORLD_REQUIRE_GPU=1 to fail instead)");
            None
        }
    }
}

/// A brick uploaded at frame N keeps stamp N through frame N + 1 when
/// no ray of that frame touches it; it used to take its slot's old
/// GPU stamp (0 for a fresh slot) at the readback, so eviction took it
/// before bricks seen longer ago.
#[test]
fn a_fresh_upload_keeps_its_stamp_through_a_frame_that_does_not_see_it() {
    let Some(ctx) = context() else { return };
    let w = terrain();
    let mut g = GpuBrickmap::streaming(
        &ctx,
        w.grid(),
        w.store().pool(),
        w.store().palette(),
        StreamConfig::default(),
    )
    .unwrap();
    let v = w.default_views()[1];
    let eye = glam::DVec3::from(v.eye);
    let cam = crate::trace::Camera::new(eye, glam::DVec3::from(v.target), v.fov, 32, 24).unwrap();
    let opts = crate::trace::RenderOptions::default();
    g.render(&ctx, &cam, &opts, w.grid(), w.store().pool())
        .unwrap();
    let first = g.frame_no;
    assert!(g.resident() > 0, "the first frame uploaded nothing");
    // Straight up from above the world: no ray meets a brick.
    let sky = crate::trace::Camera::new(
        glam::DVec3::new(32.0, 100.0, 32.0),
        glam::DVec3::new(32.0, 200.0, 32.5),
        60.0,
        32,
        24,
    )
    .unwrap();
    let (_, stats) = g
        .render(&ctx, &sky, &opts, w.grid(), w.store().pool())
        .unwrap();
    assert_eq!(stats.uploads, 0);
    let res = g.residency.as_ref().expect("streaming");
    for &slot in res.owner.keys() {
        assert_eq!(
            res.last_seen[slot as usize], first,
            "slot {slot} lost the stamp of the frame that uploaded it"
        );
    }
}

/// A pool whose arena is full of one size's blocks, then asked for
/// bricks of another size: the old blocks' holes serve only their own
/// class, so every admit evicted four bricks and failed. Compaction
/// makes room, and the GPU's arena and metadata are the mirror's.
#[test]
fn an_arena_full_of_another_sizes_holes_is_compacted() {
    let Some(ctx) = context() else { return };
    let w = terrain();
    let mut g = small_arena_pool(&ctx, &w);
    let mut stats = FrameStats::default();
    // 200 materials: 720-byte blocks, 22 of them fill 16 KiB.
    admit_all(&ctx, &mut g, (1, 0..20, 200), &mut stats);
    // Two materials: 80-byte blocks.
    admit_all(&ctx, &mut g, (2, 20..120, 2), &mut stats);
    assert!(stats.compactions > 0, "{stats:?}");
    let res = g.residency.as_ref().expect("streaming");
    assert_eq!(res.mirror.arena_holes(), 0);
    // What the GPU holds is what the mirror says.
    let (_, meta, arena) = res.mirror.raw();
    let read = |buf: &wgpu::Buffer, len: u64| -> Vec<u8> {
        let staging = ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("test readback"),
            size: len,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        enc.copy_buffer_to_buffer(buf, 0, &staging, 0, len);
        ctx.queue.submit([enc.finish()]);
        let slice = staging.slice(..);
        super::super::frame::map_read(&ctx.device, &slice)
            .unwrap()
            .to_vec()
    };
    assert_eq!(read(&g.arena, arena.len() as u64), arena, "arena");
    let n = meta.len().min(256);
    let gpu_meta = read(&g.meta, n as u64 * META_BYTES);
    assert_eq!(
        gpu_meta,
        bytemuck::cast_slice::<_, u8>(&meta[..n]),
        "metadata"
    );
}

/// When the bricks this frame has not seen hold too little to free a
/// quarter of the arena, an admit that finds the arena short evicts
/// four of them at most, as for slots, instead of every one of them
/// (review: it chased a compaction it could not reach).
#[test]
fn an_arena_that_cannot_reach_a_compaction_evicts_four_bricks_at_most() {
    let Some(ctx) = context() else { return };
    let w = terrain();
    let mut g = small_arena_pool(&ctx, &w);
    let mut stats = FrameStats::default();
    // 40 two-material bricks (80-byte blocks, 3 200 bytes) seen long ago.
    admit_all(&ctx, &mut g, (1, 0..40, 2), &mut stats);
    // This frame's: 18 of 200 materials (720 bytes each).
    admit_all(&ctx, &mut g, (2, 40..58, 200), &mut stats);
    // One of 100 materials (560 bytes) does not fit, and the old
    // bricks' 3 200 bytes cannot make the 4 096 of a compaction.
    let before = stats.evictions;
    let got = g.admit(&ctx, 58, brick(100, 58), &mut stats).unwrap();
    assert!(got.is_none());
    assert_eq!(stats.evictions - before, 4, "{stats:?}");
    assert_eq!(stats.compactions, 0);
    assert_eq!(g.resident(), 40 + 18 - 4);
}

/// On a device whose storage buffers are small, the default pool
/// shrinks to fit and the tracer still draws.
#[test]
fn a_device_with_small_buffers_gets_a_smaller_pool_that_works() {
    let Some(mut ctx) = context() else { return };
    ctx.limits.max_storage_buffer_binding_size = 1 << 20;
    let w = terrain();
    let mut g = GpuBrickmap::streaming(
        &ctx,
        w.grid(),
        w.store().pool(),
        w.store().palette(),
        StreamConfig::default(),
    )
    .unwrap();
    let cfg = g.residency.as_ref().expect("streaming").cfg;
    assert_eq!(cfg.pool_slots, (1 << 20) / 64);
    assert_eq!(cfg.arena_bytes, 1 << 20);
    let v = w.default_views()[1];
    let cam_of = |width, height| {
        let (eye, target) = (glam::DVec3::from(v.eye), glam::DVec3::from(v.target));
        crate::trace::Camera::new(eye, target, v.fov, width, height).unwrap()
    };
    let cam = cam_of(32, 24);
    let opts = crate::trace::RenderOptions::default();
    for _ in 0..4 {
        g.render(&ctx, &cam, &opts, w.grid(), w.store().pool())
            .unwrap();
    }
    assert!(g.resident() > 0);
    // A frame whose pixel buffer passes the limit is an error with the
    // figures, not a wgpu validation panic (regression: 3840×2160 on
    // lavapipe); the tracer goes on drawing smaller frames.
    let Err(e) = g.render(&ctx, &cam_of(256, 256), &opts, w.grid(), w.store().pool()) else {
        panic!("a 256x256 frame fitted a 1 MiB buffer limit");
    };
    assert!(
        e.to_string().contains("a 256x256 frame needs") && e.to_string().contains("1048576"),
        "{e}"
    );
    g.render(&ctx, &cam, &opts, w.grid(), w.store().pool())
        .unwrap();
}
