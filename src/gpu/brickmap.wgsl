// The GPU brickmap tracer: the same exact hierarchical DDA as the CPU
// (src/trace/dda.rs) and the same level walk (src/trace/lod.rs), in WGSL.
//
// One invocation per pixel: build the DESIGN §3 camera ray, enter the grid,
// walk the levels of src/world/mip.rs (32, 16, 8, 4, 2, 1 voxels per cell)
// skipping empty cells exactly, stop at the level the pixel footprint allows
// (P.lod_k = C * pixel angle; 0 is exact), shade with Lambert (+ an optional
// shadow ray, always exact).
//
// WGSL implementations may treat infinities as indeterminate, so switched-off
// axes use a large finite crossing time (BIG) instead of +inf.
//
// Streaming (van Wingerden §4.1): a grid pointer's top two bits give its state.
//   0x00000000          empty
//   0b01 << 30 | m << 16 | lod565
//                       unloaded: a ray whose footprint takes the brick whole
//                       (level >= 3) hits it with material m and asks nothing;
//                       a finer one shades it with its LOD colour and
//                       request it (once: compare-exchange to "requested", then
//                       append to the bounded feedback buffer; on overflow the
//                       pointer goes back to unloaded, so the request is simply
//                       made again next frame). The ray then walks on through
//                       the brick, for requests only (up to WALK_THROUGH LOD
//                       bricks), so a frame asks for everything up to the
//                       real surface and bricks revealed by an edit arrive
//                       with it.
//   0b10 << 30 | m << 16 | lod565 requested: LOD colour, no new request
//   0b11 << 30 | m      uniform brick of material m
//   otherwise           loaded: GPU pool slot + 1 (its last-seen frame is stamped)

// How many unloaded bricks a ray walks through, asking for each, before it
// settles for the first one's LOD colour. Swept on terrain 2048² at C = 1
// (`bench stream`, medium view; twenty-second session): 8 → 34.8 % of the
// world's brick data resident, 6 → 34.3, 4 → 32.8, 3 → 35.4, 2 → 33.2; edits
// visible within 2 frames down to 3, in 3 frames at 2. 4 was lower than 8
// in all three views (41.8 / 32.8 / 27.1 % against 42.2 / 34.8 / 28.6) and
// converged in 9 to 12 % fewer frames.
const WALK_THROUGH: i32 = 4;

struct Params {
    eye: vec3<f32>, tan_half: f32,
    f: vec3<f32>, aspect: f32,
    r: vec3<f32>, ambient: f32,
    u: vec3<f32>, shadows: u32,
    light: vec3<f32>, width: u32,
    dims: vec3<i32>, height: u32,   // grid size in voxels
    anchor: vec3<i32>, frame: u32,  // world voxel of local (0, 0, 0); frame number
    feedback_capacity: u32, ring_x: i32, ring_y: i32, ring_z: i32, // ring: physical brick of local (0, 0, 0)
    fog: f32, lod_k: f32, l4_offset: u32, ao: u32,  // fog extent (0: none); C * pixel angle (0: exact); level 4's word offset in `coarse`
    jitter: vec2<f32>, beam: u32, image_only: u32,    // where primary rays pass in each pixel; beam starts on (1); colour alone, into `image` (1)
};

struct PixelOut {
    rgba: u32,
    depth: f32,
    vx: i32,
    vy: i32,
    vz: i32,
    normal: u32, // 0: miss; else 1 + axis*2 + (sign > 0); 7: started inside; +8: LOD (brick not loaded)
};

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read_write> grid: array<atomic<u32>>;
@group(0) @binding(2) var<storage, read> coarse: array<u32>; // levels 5 then 4: material bytes
@group(0) @binding(3) var<storage, read> masks: array<u32>;   // 16 words per slot
@group(0) @binding(4) var<storage, read> bmeta: array<u32>;   // 4 words per slot: data, flags | material << 8, octant materials x2
@group(0) @binding(5) var<storage, read> arena: array<u32>;   // material arena bytes
@group(0) @binding(6) var<storage, read> palette: array<u32>; // 256 x 0x00BBGGRR
@group(0) @binding(7) var<storage, read_write> out: array<PixelOut>;
@group(0) @binding(8) var<storage, read_write> feedback: array<atomic<u32>>; // [0] = count, then brick indices
@group(0) @binding(9) var<storage, read_write> last_seen: array<u32>;        // per pool slot
@group(0) @binding(10) var<storage, read_write> beams: array<f32>;           // per 8x8 block: where its rays start
@group(0) @binding(11) var<storage, read_write> image: array<u32>;          // per pixel 0xAABBGGRR, when P.image_only

const BIG: f32 = 1e30;
const STATE_MASK: u32 = 0xC0000000u;
const UNLOADED: u32 = 0x40000000u;
const REQUESTED: u32 = 0x80000000u;
const UNIFORM: u32 = 0xC0000000u;
const FLAG_MULTI: u32 = 2u;

struct Ray {
    o: vec3<f32>,
    d: vec3<f32>,
    inv: vec3<f32>,
    step: vec3<i32>,
    plane: vec3<i32>,
    act: vec3<bool>,
};

struct State {
    cell: vec3<i32>,
    tmax: vec3<f32>,
    t: f32,
    axes: u32,
};

fn make_ray(o: vec3<f32>, d: vec3<f32>) -> Ray {
    var r: Ray;
    r.o = o;
    r.d = d;
    for (var a = 0; a < 3; a++) {
        let act = abs(d[a]) > 1e-30;
        r.act[a] = act;
        r.inv[a] = select(0.0, 1.0 / d[a], act);
        r.step[a] = select(0, select(-1, 1, d[a] > 0.0), act);
        r.plane[a] = select(0, 1, d[a] < 0.0);
    }
    return r;
}

fn crossing(r: Ray, a: i32, c: i32) -> f32 {
    return select(BIG, (f32(c + r.plane[a]) - r.o[a]) * r.inv[a], r.act[a]);
}

// (cell, next crossing, stepped exactly at t) on axis a after all crossings <= t.
struct AxisAfter { c: i32, next: f32, at: bool };

fn axis_after(r: Ray, a: i32, t: f32, start: i32) -> AxisAfter {
    var res: AxisAfter;
    if (!r.act[a]) {
        res.c = start; res.next = BIG; res.at = false;
        return res;
    }
    let s = r.step[a];
    let est = i32(floor(clamp(r.o[a] + t * r.d[a], -3.0e7, 3.0e7)));
    var c = select(min(est, start), max(est, start), s > 0);
    var next = crossing(r, a, c + s);
    var guard = 0;
    while (next <= t && guard < 4096) {
        c += s;
        next = crossing(r, a, c + s);
        guard++;
    }
    var at = false;
    while (c != start && guard < 8192) {
        let cur = crossing(r, a, c);
        if (cur > t) {
            next = cur;
            c -= s;
            guard++;
        } else {
            at = cur == t;
            break;
        }
    }
    res.c = c; res.next = next; res.at = at;
    return res;
}

fn advance_to(r: Ray, st: ptr<function, State>, t: f32) {
    var axes = 0u;
    for (var a = 0; a < 3; a++) {
        if ((*st).tmax[a] > t) { continue; }
        let x = axis_after(r, a, t, (*st).cell[a]);
        (*st).cell[a] = x.c;
        (*st).tmax[a] = x.next;
        if (x.at) { axes |= 1u << u32(a); }
    }
    (*st).t = t;
    (*st).axes = axes;
}

fn floor_i(x: f32) -> i32 { return i32(floor(x)); }

// Enter [0, hi); returns false if the ray never spends length inside.
fn enter(r: Ray, hi: vec3<i32>, st: ptr<function, State>) -> bool {
    let start = vec3<i32>(floor_i(r.o.x), floor_i(r.o.y), floor_i(r.o.z));
    var t_enter = 0.0;
    var outside = false;
    for (var a = 0; a < 3; a++) {
        if (start[a] < 0 || start[a] >= hi[a]) {
            outside = true;
            let first = select(hi[a] - 1, 0, start[a] < 0);
            let moving_in = (start[a] < 0 && r.step[a] > 0) || (start[a] >= hi[a] && r.step[a] < 0);
            if (!moving_in) { return false; }
            t_enter = max(t_enter, crossing(r, a, first));
        }
    }
    (*st).cell = start;
    (*st).t = 0.0;
    (*st).axes = 0u;
    for (var a = 0; a < 3; a++) {
        (*st).tmax[a] = crossing(r, a, start[a] + r.step[a]);
    }
    if (!outside) { return true; }
    advance_to(r, st, t_enter);
    for (var a = 0; a < 3; a++) {
        if ((*st).cell[a] < 0 || (*st).cell[a] >= hi[a]) { return false; }
    }
    return true;
}

fn step_fine(r: Ray, st: ptr<function, State>) {
    let t = min((*st).tmax.x, min((*st).tmax.y, (*st).tmax.z));
    var axes = 0u;
    for (var a = 0; a < 3; a++) {
        if ((*st).tmax[a] == t) {
            (*st).cell[a] += r.step[a];
            (*st).tmax[a] = crossing(r, a, (*st).cell[a] + r.step[a]);
            axes |= 1u << u32(a);
        }
    }
    (*st).t = t;
    (*st).axes = axes;
}


fn coarse_exit(r: Ray, a: i32, c: i32, shift: u32) -> i32 {
    return select((c << shift) - 1, (c + 1) << shift, r.step[a] > 0);
}

fn coarse_tmax(r: Ray, c: vec3<i32>, shift: u32) -> vec3<f32> {
    var t: vec3<f32>;
    for (var a = 0; a < 3; a++) { t[a] = crossing(r, a, coarse_exit(r, a, c[a], shift)); }
    return t;
}

fn inside(c: vec3<i32>, hi: vec3<i32>) -> bool {
    return all(c >= vec3<i32>(0)) && all(c < hi);
}

// Toroidal addressing: local cell c of a grid of d cells lives at
// physical cell (c + ring) mod d (the ring is zero unless the grid slid).
fn wrap(c: vec3<i32>, d: vec3<i32>) -> vec3<i32> {
    return select(c, c - d, c >= d);
}

fn ring() -> vec3<i32> {
    return vec3<i32>(P.ring_x, P.ring_y, P.ring_z);
}

fn brick_index(b: vec3<i32>) -> u32 {
    let bd = P.dims >> vec3<u32>(3u);
    let p = wrap(b + ring(), bd);
    return u32(p.x + bd.x * (p.y + bd.y * p.z));
}

fn pointer(b: vec3<i32>) -> u32 {
    return atomicLoad(&grid[brick_index(b)]);
}

// Ask for an unloaded brick, once per brick however many rays reach it.
fn request(b: vec3<i32>, p: u32) {
    let i = brick_index(b);
    let claimed = atomicCompareExchangeWeak(&grid[i], p, (p & ~STATE_MASK) | REQUESTED);
    if (claimed.exchanged) {
        let n = atomicAdd(&feedback[0], 1u);
        if (n < P.feedback_capacity) {
            atomicStore(&feedback[n + 1u], i);
        } else {
            // Overflow: undo the claim so that a later frame asks again.
            atomicStore(&grid[i], p);
        }
    }
}

fn unpack565(v: u32) -> u32 {
    let r = (v >> 11u) & 31u;
    let g = (v >> 5u) & 63u;
    let b = v & 31u;
    return ((r << 3u) | (r >> 2u)) | (((g << 2u) | (g >> 4u)) << 8u) | (((b << 3u) | (b >> 2u)) << 16u);
}

fn arena_byte(k: u32) -> u32 {
    return (arena[k >> 2u] >> (8u * (k & 3u))) & 0xffu;
}

fn brick_material(slot: u32, idx: u32) -> u32 {
    let data = bmeta[slot * 4u];
    let flags = bmeta[slot * 4u + 1u];
    if ((flags & FLAG_MULTI) == 0u) { return data & 0xffu; }
    let word = idx >> 5u;
    var rank = 0u;
    for (var w = 0u; w < word; w++) { rank += countOneBits(masks[slot * 16u + w]); }
    rank += countOneBits(masks[slot * 16u + word] & ((1u << (idx & 31u)) - 1u));
    let pal_len = arena_byte(data);
    let bits = arena_byte(data + 1u);
    let bit = rank * bits;
    let local = (arena_byte(data + 3u + pal_len + (bit >> 3u)) >> (bit & 7u)) & ((1u << bits) - 1u);
    return arena_byte(data + 3u + local);
}

struct Hit { found: bool, t: f32, cell: vec3<i32>, normal: vec3<i32>, material: u32, lod: bool, rgb: u32, level: u32, slot: u32, loaded: bool };

fn hit_of(r: Ray, st: State, m: u32) -> Hit {
    var h: Hit;
    h.found = true;
    h.t = st.t;
    h.cell = st.cell;
    h.material = m;
    h.lod = false;
    h.rgb = palette[m];
    h.level = 0u;
    h.slot = 0u;
    h.loaded = false;
    h.normal = vec3<i32>(0);
    if (st.axes != 0u) {
        let a = i32(firstTrailingBit(st.axes));
        h.normal[a] = -r.step[a];
    }
    return h;
}

fn select_lod(lod: Hit, other: Hit) -> Hit {
    if (lod.found) { return lod; }
    return other;
}

// Skip the empty aligned cube of edge 1 << shift holding the current cell
// (src/trace/dda.rs, DdaRay::skip).
fn skip(r: Ray, st: ptr<function, State>, shift: u32) {
    if (shift == 0u) { step_fine(r, st); return; }
    let size = 1 << shift;
    var t = BIG;
    for (var a = 0; a < 3; a++) {
        let base = ((*st).cell[a] >> shift) << shift;
        let exit = select(base - 1, base + size, r.step[a] > 0);
        t = min(t, crossing(r, a, exit));
    }
    advance_to(r, st, t);
}

// The level a footprint of w voxels allows (src/trace/lod.rs, lod_level).
fn lod_level(w: f32) -> u32 {
    if (w < 2.0) { return 0u; }
    if (w < 4.0) { return 1u; }
    if (w < 8.0) { return 2u; }
    if (w < 16.0) { return 3u; }
    if (w < 32.0) { return 4u; }
    return 5u;
}

// Material byte of the level-4 or level-5 cell holding local voxel c (0: empty).
fn coarse_mat(level: u32, c: vec3<i32>) -> u32 {
    let d = P.dims >> vec3<u32>(level);
    let p = wrap((c >> vec3<u32>(level)) + (ring() >> vec3<u32>(level - 3u)), d);
    let k = select(0u, P.l4_offset * 4u, level == 4u) + u32(p.x + d.x * (p.y + d.y * p.z));
    return (coarse[k >> 2u] >> (8u * (k & 3u))) & 0xffu;
}

// Whether the level-0, 1 or 2 cell holding brick-local voxel l is solid
// (src/world/mip.rs, block_solid): a few masked words of the brick mask.
fn block_solid(slot: u32, level: u32, l: vec3<i32>) -> bool {
    let base = slot * 16u;
    if (level == 0u) {
        let i = u32(l.x | (l.y << 3u) | (l.z << 6u));
        return ((masks[base + (i >> 5u)] >> (i & 31u)) & 1u) != 0u;
    }
    let e = 1 << level;
    let b = l & vec3<i32>(~(e - 1));
    let hi = u32(b.y >> 2u);
    var bits = 0x0F0F0F0Fu << u32(b.x);
    if (level == 1u) { bits = 0x303u << u32(b.x + 8 * (b.y & 3)); }
    var acc = 0u;
    for (var z = b.z; z < b.z + e; z++) { acc |= masks[base + u32(z) * 2u + hi]; }
    return (acc & bits) != 0u;
}

// Material of a hit at `level` on local voxel c, in the brick of GPU pointer p.
fn lod_material(level: u32, c: vec3<i32>, p: u32, slot: u32, loaded: bool) -> u32 {
    if (level >= 4u) { return coarse_mat(level, c); }
    let state = p & STATE_MASK;
    if (state == UNIFORM) { return p & 0xffu; }
    if (!loaded) { return (p >> 16u) & 0xffu; }
    let l = c & vec3<i32>(7);
    if (level == 0u) { return brick_material(slot, u32(l.x | (l.y << 3u) | (l.z << 6u))); }
    if (level == 3u) { return (bmeta[slot * 4u + 1u] >> 8u) & 0xffu; }
    let o = u32((l.x >> 2u) | ((l.y >> 2u) << 1u) | ((l.z >> 2u) << 2u));
    return (bmeta[slot * 4u + 2u + (o >> 2u)] >> (8u * (o & 3u))) & 0xffu;
}

// The level walk of src/trace/lod.rs: at the current voxel, check levels from
// the highest whose cell changed down to the level the footprint allows
// (k = C * pixel angle; 0 is exact); skip the first empty one exactly, or hit.
fn trace(o: vec3<f32>, d: vec3<f32>, k: f32, t_start: f32) -> Hit {
    var miss: Hit;
    miss.found = false;
    let r = make_ray(o, d);
    if (!any(r.act)) { return miss; }
    var st: State;
    if (!enter(r, P.dims, &st)) { return miss; }
    // A beam start: restore the exact state there (src/trace/beam.rs).
    if (t_start > st.t) {
        advance_to(r, &st, t_start);
        if (!inside(st.cell, P.dims)) { return miss; }
    }
    var lod_hit: Hit;
    lod_hit.found = false;
    var lod_count = 0;
    var top = 5u;
    var p = 0u;
    var slot = 0u;
    var loaded = false;
    for (var guard = 0; guard < 1000000; guard++) {
        let allowed = lod_level(st.t * k);
        let c = st.cell;
        var level = top;
        var hit_level = -1;
        loop {
            var solid = true;
            if (level >= 4u) {
                solid = coarse_mat(level, c) != 0u;
            } else if (level == 3u) {
                let bc = c >> vec3<u32>(3u);
                p = pointer(bc);
                let state = p & STATE_MASK;
                loaded = p != 0u && state == 0u;
                if (loaded) {
                    slot = p - 1u;
                    last_seen[slot] = P.frame;
                }
                solid = p != 0u;
                if ((state == UNLOADED || state == REQUESTED) && allowed < 3u) {
                    // Needed finer than it is here: ask for it, show its
                    // colour, and walk on through it for requests only.
                    if (state == UNLOADED) { request(bc, p); }
                    if (!lod_hit.found) {
                        lod_hit = hit_of(r, st, 0u);
                        lod_hit.lod = true;
                        lod_hit.rgb = unpack565(p & 0xffffu);
                    }
                    lod_count++;
                    if (lod_count >= WALK_THROUGH) { return lod_hit; }
                    solid = false;
                } else if (solid && lod_hit.found) {
                    return lod_hit;
                }
            } else if (loaded) {
                solid = block_solid(slot, level, c & vec3<i32>(7));
            }
            if (!solid) { break; }
            if (level <= allowed) {
                hit_level = i32(level);
                break;
            }
            level -= 1u;
        }
        if (hit_level >= 0) {
            if (lod_hit.found) { return lod_hit; }
            var h = hit_of(r, st, lod_material(u32(hit_level), c, p, slot, loaded));
            h.level = u32(hit_level);
            h.slot = slot;
            h.loaded = loaded;
            return h;
        }
        skip(r, &st, level);
        if (!inside(st.cell, P.dims)) { return select_lod(lod_hit, miss); }
        let ch = (c.x ^ st.cell.x) | (c.y ^ st.cell.y) | (c.z ^ st.cell.z);
        top = min(firstLeadingBit(u32(ch)), 5u);
    }
    return select_lod(lod_hit, miss);
}

// Word w (of 16) of the mask of local brick b: empty outside the grid or for
// an empty brick, full for a uniform one or one not loaded (unknown here:
// solid, as for ambient occlusion).
fn mask_word(b: vec3<i32>, w: u32) -> u32 {
    if (any(b < vec3<i32>(0)) || any(b >= (P.dims >> vec3<u32>(3u)))) { return 0u; }
    let p = pointer(b);
    if (p == 0u) { return 0u; }
    let state = p & STATE_MASK;
    if (state == UNIFORM) { return 0xffffffffu; }
    if (state == 0u) { return masks[(p - 1u) * 16u + w]; }
    return 0xffffffffu;
}

// A coarse hit on a 2- or 4-voxel cell of a loaded brick: its exposed voxel
// faces' colours lit by Lambert, averaged by the area each shows along d
// (src/trace/render.rs, coarse_average). w = 0: nothing to average.
fn coarse_average(hit: Hit, d: vec3<f32>) -> vec4<f32> {
    let e = 1 << hit.level;
    let lc = hit.cell & vec3<i32>(7);
    let bl = lc & vec3<i32>(~(e - 1));
    let b = hit.cell >> vec3<u32>(3u);
    let hi = u32(bl.y >> 2u);            // which half-word (rows 0-3 or 4-7)
    let y0 = bl.y & 3;
    let row = ((1u << u32(e)) - 1u) << u32(bl.x);
    var cellm = 0u;
    for (var y = y0; y < y0 + e; y++) { cellm |= row << u32(8 * y); }
    let base = hit.slot * 16u;
    var sum = vec3<f32>(0.0);
    var weight = 0.0;
    for (var z = bl.z; z < bl.z + e; z++) {
        let wi = u32(z) * 2u + hi;
        let h = masks[base + wi];
        let wv = h & cellm;
        if (wv == 0u) { continue; }
        var nbr: array<u32, 6>;
        nbr[0] = ((h >> 1u) & ~0x80808080u) | ((mask_word(b + vec3<i32>(1, 0, 0), wi) & 0x01010101u) << 7u);
        nbr[1] = ((h << 1u) & ~0x01010101u) | ((mask_word(b - vec3<i32>(1, 0, 0), wi) & 0x80808080u) >> 7u);
        var above = 0u;
        var below = 0u;
        if (hi == 0u) {
            above = masks[base + wi + 1u] & 0xffu;
            below = (mask_word(b - vec3<i32>(0, 1, 0), wi + 1u) >> 24u) & 0xffu;
        } else {
            above = mask_word(b + vec3<i32>(0, 1, 0), wi - 1u) & 0xffu;
            below = (masks[base + wi - 1u] >> 24u) & 0xffu;
        }
        nbr[2] = (h >> 8u) | (above << 24u);
        nbr[3] = (h << 8u) | below;
        if (z < 7) { nbr[4] = masks[base + wi + 2u]; } else { nbr[4] = mask_word(b + vec3<i32>(0, 0, 1), hi); }
        if (z > 0) { nbr[5] = masks[base + wi - 2u]; } else { nbr[5] = mask_word(b - vec3<i32>(0, 0, 1), 14u + hi); }
        for (var k = 0; k < 6; k++) {
            var n = vec3<f32>(0.0);
            n[k / 2] = select(1.0, -1.0, (k & 1) != 0);
            let wgt = max(-dot(n, d), 0.0);
            var bits = wv & ~nbr[k];
            if (bits == 0u || wgt <= 0.0) { continue; }
            let light = P.ambient + (1.0 - P.ambient) * max(dot(n, P.light), 0.0);
            loop {
                if (bits == 0u) { break; }
                let bit = firstTrailingBit(bits);
                bits &= bits - 1u;
                let i = u32(z) * 64u + hi * 32u + bit;
                sum += unpack_rgb(palette[brick_material(hit.slot, i)]) * light * wgt;
                weight += wgt;
            }
        }
    }
    return vec4<f32>(sum, weight);
}

// Whether local voxel c is solid, for ambient occlusion. A brick not loaded
// counts as solid (its voxels are unknown here); preloaded pools are exact.
fn solid_at(c: vec3<i32>) -> bool {
    if (!inside(c, P.dims)) { return false; }
    let p = pointer(c >> vec3<u32>(3u));
    if (p == 0u) { return false; }
    if ((p & STATE_MASK) == 0u) { return block_solid(p - 1u, 0u, c & vec3<i32>(7)); }
    return true;
}

// Openness of the face of voxel `cell` with normal n at hit point p
// (src/trace/ao.rs, face_ao): the classic voxel corner rule, interpolated.
fn face_ao(cell: vec3<i32>, n: vec3<i32>, p: vec3<f32>) -> f32 {
    if (all(n == vec3<i32>(0))) { return 1.0; }
    var a = 0;
    if (n.y != 0) { a = 1; }
    if (n.z != 0) { a = 2; }
    let u = (a + 1) % 3;
    let v = (a + 2) % 3;
    var eu = vec3<i32>(0);
    eu[u] = 1;
    var ev = vec3<i32>(0);
    ev[v] = 1;
    let f = cell + n;
    var cs: array<f32, 4>;
    for (var k = 0; k < 4; k++) {
        let su = select(-1, 1, (k & 1) != 0);
        let sv = select(-1, 1, (k & 2) != 0);
        let s1 = u32(solid_at(f + eu * su));
        let s2 = u32(solid_at(f + ev * sv));
        let c = u32(solid_at(f + eu * su + ev * sv));
        cs[k] = select(f32(3u - s1 - s2 - c) / 3.0, 0.0, s1 + s2 == 2u);
    }
    let fu = clamp(p[u] - f32(cell[u]), 0.0, 1.0);
    let fv = clamp(p[v] - f32(cell[v]), 0.0, 1.0);
    let low = cs[0] + (cs[1] - cs[0]) * fu;
    let high = cs[2] + (cs[3] - cs[2]) * fu;
    return low + (high - low) * fv;
}

// Beam starts (src/trace/beam.rs): whether the 3x3x3 level-`level` cells
// (3, 4 or 5) around c are empty.
fn neighbourhood_empty(c: vec3<i32>, level: u32) -> bool {
    let n = P.dims >> vec3<u32>(level);
    for (var dz = -1; dz <= 1; dz++) {
        for (var dy = -1; dy <= 1; dy++) {
            for (var dx = -1; dx <= 1; dx++) {
                let q = c + vec3<i32>(dx, dy, dz);
                if (any(q < vec3<i32>(0)) || any(q >= n)) { continue; }
                if (level == 3u) {
                    if (pointer(q) != 0u) { return false; }
                } else if (coarse_mat(level, q << vec3<u32>(level)) != 0u) {
                    return false;
                }
            }
        }
    }
    return true;
}

// A distance before which every ray within `spread` of the centre ray meets
// nothing (BrickmapTracer::beam_start).
fn beam_start(o: vec3<f32>, d: vec3<f32>, spread: f32, k: f32) -> f32 {
    let r = make_ray(o, d);
    if (!any(r.act)) { return 0.0; }
    // From the eye, even outside the grid (see src/trace/beam.rs).
    var level = 3u;
    var cc = vec3<i32>(floor(o)) >> vec3<u32>(level);
    var ct = coarse_tmax(r, cc, level);
    var t_in = 0.0;
    for (var guard = 0; guard < 4096; guard++) {
        var t_out = min(ct.x, min(ct.y, ct.z));
        loop {
            if (t_out * spread * 1.5 < f32(1u << level)) { break; }
            if (level == 5u) { return t_in; }
            level += 1u;
            cc = cc >> vec3<u32>(1u);
            ct = coarse_tmax(r, cc, level);
            t_out = min(ct.x, min(ct.y, ct.z));
        }
        // An off-centre ray is at t_out * sqrt(1 + spread^2) when it projects to t_out.
        if (lod_level(t_out * k * sqrt(1.0 + spread * spread)) > level || !neighbourhood_empty(cc, level)) { return t_in; }
        for (var a = 0; a < 3; a++) {
            if (ct[a] == t_out) {
                cc[a] += r.step[a];
                ct[a] = crossing(r, a, coarse_exit(r, a, cc[a], level));
            }
        }
        t_in = t_out;
        let n = P.dims >> vec3<u32>(level);
        for (var a = 0; a < 3; a++) {
            if ((cc[a] < -1 && r.step[a] <= 0) || (cc[a] > n[a] && r.step[a] >= 0)) { return t_in; }
        }
    }
    return t_in;
}

fn pixel_dir(x: f32, y: f32) -> vec3<f32> {
    let a = (x / f32(P.width) * 2.0 - 1.0) * P.tan_half * P.aspect;
    let b = (1.0 - y / f32(P.height) * 2.0) * P.tan_half;
    return normalize(P.f + a * P.r + b * P.u);
}

// The coarse pass: one invocation per 8x8 block of pixels.
@compute @workgroup_size(8, 8)
fn beam_pass(@builtin(global_invocation_id) gid: vec3<u32>) {
    let bw = (P.width + 7u) / 8u;
    let bh = (P.height + 7u) / 8u;
    if (gid.x >= bw || gid.y >= bh) { return; }
    let x0 = f32(gid.x * 8u);
    let y0 = f32(gid.y * 8u);
    let x1 = f32(min((gid.x + 1u) * 8u, P.width));
    let y1 = f32(min((gid.y + 1u) * 8u, P.height));
    let c = pixel_dir((x0 + x1) * 0.5, (y0 + y1) * 0.5);
    var spread = 0.0;
    for (var k = 0; k < 4; k++) {
        let dc = pixel_dir(select(x0, x1, (k & 1) != 0), select(y0, y1, (k & 2) != 0));
        spread = max(spread, length(cross(dc, c)) / max(dot(dc, c), 1e-9));
    }
    let t = beam_start(P.eye, c, spread, P.lod_k);
    beams[gid.y * bw + gid.x] = max(t * (1.0 - 1e-3) - 0.05, 0.0);
}

fn unpack_rgb(c: u32) -> vec3<f32> {
    return vec3<f32>(f32(c & 0xffu), f32((c >> 8u) & 0xffu), f32((c >> 16u) & 0xffu)) / 255.0;
}

fn sky(d: vec3<f32>) -> vec3<f32> {
    let k = clamp(d.y, 0.0, 1.0);
    return mix(vec3<f32>(0.78, 0.86, 0.95), vec3<f32>(0.33, 0.52, 0.84), k);
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= P.width || gid.y >= P.height) { return; }
    let d = pixel_dir(f32(gid.x) + P.jitter.x, f32(gid.y) + P.jitter.y);
    var t0 = 0.0;
    if (P.beam != 0u) { t0 = beams[(gid.y / 8u) * ((P.width + 7u) / 8u) + gid.x / 8u]; }
    let hit = trace(P.eye, d, P.lod_k, t0);
    var o: PixelOut;
    var color: vec3<f32>;
    if (hit.found) {
        var avg = vec4<f32>(0.0);
        if ((hit.level == 1u || hit.level == 2u) && hit.loaded) { avg = coarse_average(hit, d); }
        let n = vec3<f32>(hit.normal);
        var lambert = max(dot(n, P.light), 0.0);
        if (P.shadows != 0u && lambert > 0.0 && avg.w <= 0.0) {
            let cell = hit.cell + hit.normal;
            let p = P.eye + d * hit.t;
            let lo = vec3<f32>(cell);
            let hi = vec3<f32>(cell + vec3<i32>(1));
            // Largest f32 below hi: one ulp down (the cells' bounds are exact).
            let below = bitcast<vec3<f32>>(bitcast<vec3<u32>>(hi) - vec3<u32>(select(vec3<u32>(0u), vec3<u32>(1u), hi > vec3<f32>(0.0)))) ;
            let hi2 = select(below, -bitcast<vec3<f32>>(bitcast<vec3<u32>>(-hi) + vec3<u32>(1u)), hi <= vec3<f32>(0.0));
            let q = clamp(p, lo, hi2);
            if (trace(q, P.light, 0.0, 0.0).found) { lambert = 0.0; }
        }
        let k = select(P.ambient + (1.0 - P.ambient) * lambert, P.ambient, all(hit.normal == vec3<i32>(0)));
        color = unpack_rgb(hit.rgb) * k;
        if (avg.w > 0.0) { color = avg.xyz / avg.w; }
        if (P.ao != 0u) {
            color *= 1.0 - 0.45 * (1.0 - face_ao(hit.cell, hit.normal, P.eye + d * hit.t));
        }
        if (P.fog > 0.0) {
            color = mix(color, sky(d), 1.0 - exp(-hit.t / P.fog));
        }
        o.depth = hit.t;
        let world = hit.cell + P.anchor;
        o.vx = world.x; o.vy = world.y; o.vz = world.z;
        var code = 7u;
        for (var ax = 0; ax < 3; ax++) {
            if (hit.normal[ax] != 0) { code = 1u + u32(ax) * 2u + select(0u, 1u, hit.normal[ax] > 0); }
        }
        o.normal = code + select(0u, 8u, hit.lod);
    } else {
        color = sky(d);
        o.depth = -1.0;
        o.normal = 0u;
    }
    let c = vec3<u32>(clamp(color, vec3<f32>(0.0), vec3<f32>(1.0)) * 255.0 + 0.5);
    o.rgba = c.x | (c.y << 8u) | (c.z << 16u) | (255u << 24u);
    let idx = gid.y * P.width + gid.x;
    if (P.image_only != 0u) { image[idx] = o.rgba; } else { out[idx] = o; }
}
