--!strict
-- water3d.lua: volumetric water over the raw bricks, hydrostatic.
--
-- Every open cell (air or water) holds a fill `water` (1 = a full voxel).
-- Water is slightly compressible: a full cell under d cells of water holds
-- about 1 + d * compress. That small excess is the pressure, and it is what
-- makes this a real hydrostatic model: water pushed down one arm of a
-- U-tube compresses the cells at the bottom, flows through the tunnel, and
-- rises in the other arm until both surfaces stand at one level
-- (communicating vessels), which a fill level alone cannot do.
--
-- Flux form, in two passes, so water is conserved to round-off whatever the
-- thread count. Both passes walk the brick's faces, not its cells: each
-- face's flux is computed once and applied to the cells on both sides (a
-- face on the brick's border is computed by both bricks with the same
-- formula and the same inputs, so both agree to the bit):
--   limit: each cell sums what it would send through its six faces and
--          stores k = min(1, fill / outflow), so it never sends more than
--          it holds (0 where it sends nothing);
--   flow:  each face's flux, scaled by the sender's k, moves water from one
--          cell to the other. A cell is drawn as water when it is at least
--          half full.
--
-- Sums are kept in f64 in a scratch buffer made inside the kernel (a kernel
-- keeps no state between calls); fills are stored as f32. Each face kind
-- (x, z, then vertical) has its own loop, walking along its axis and
-- carrying the previous face's share to the next cell, so every cell is
-- read once per axis: a shared helper would cost a call per face.
--
-- Only supported water spreads sideways: a cell sends through a side face
-- only if what is below it is solid or cannot take all of it. Water in the
-- air falls; it does not smear sideways into a mist. And only what a cell
-- holds above a thin `film` spreads (the residual water wet ground keeps),
-- so a puddle stops growing and its bricks sleep.
--
-- Free fall: where the water of two stacked cells fits in the lower one,
-- all of the upper cell's water falls into it in one tick, so a falling
-- drop stays one compact voxel and moves one voxel per tick (only the
-- lower's pushing back, in fuller water, can oscillate: `fall` rules there).
--
-- Faces into solid cells (anything but air and water, and the world's
-- boundary) carry nothing. Fluxes below `still` are dropped on both sides
-- alike, so water at rest stops changing exactly and its bricks sleep.

local readf32, writef32 = buffer.readf32, buffer.writef32
local readf64, writef64 = buffer.readf64, buffer.writef64
local readu8, writeu8 = buffer.readu8, buffer.writeu8
local create = buffer.create
local max = math.max

-- Halo strides (x fastest, then y, then z, 10 per axis).
local DY, DZ = 10, 100
-- Stability. This is an explicit scheme: in compressed water every face
-- relaxes its two cells towards each other, sideways at `spread` and
-- vertically at about fall / 2 per tick, and the fastest (checkerboard)
-- mode stops decaying once 2 * spread + fall / 2 passes 1/2 (`verify sims`'
-- voxel_stability case measures exactly that breaking point). Past this
-- margin both rates are scaled down together, so any parameters in their
-- ranges settle: the flow is slower than asked, never unstable.
local STABLE = 0.45
-- The fill the lower of two stacked cells holds at rest, given their total
-- t and the compressibility: all of it up to one cell, then the excess
-- shared so that the lower cell holds `comp` more than the upper.
local function lower(t: number, comp: number): number
  if t <= 1 then
    return t
  elseif t < 2 + comp then
    return (1 + t * comp) / (1 + comp)
  else
    return (t + comp) / 2
  end
end


return {
  grid = "voxels",
  channels = { "water", "k" },
  nonnegative = { "water" },
  conserved = { "water" },
  materials = { "water" },
  only = { "water" },
  -- A freshly built world's water voxels start full.
  fills = { water = "water" },
  params = {
    compress = { default = 0.02, min = 0.0, max = 0.2 },
    fall = { default = 0.3, min = 0.0, max = 1.0 },
    -- A film this thin stays where it is (it can still fall): a drop on
    -- open ground makes a puddle and stops, instead of spreading forever.
    film = { default = 0.02, min = 0.0, max = 0.5 },
    spread = { default = 0.15, min = 0.0, max = 0.5 },
    still = { default = 1e-5, min = 0.0, max = 0.01 },
  },

  passes = {
    {
      name = "limit",
      reads = { "water" },
      writes = { "k" },
      kernel = function(c, bx: number, by: number, bz: number)
        local W: buffer, M: buffer, K: buffer = c.r.water, c.r.mat, c.w.k
        local WATER: number = c.m.water
        local comp: number, fall: number, spread: number, still: number =
          c.p.compress, c.p.fall, c.p.spread, c.p.still
        local film: number = c.p.film
        local sum = 2 * spread + 0.5 * fall
        if sum > STABLE then
          local r = STABLE / sum
          spread, fall = spread * r, fall * r
        end
        -- What each cell would send (f > 0: a sends to b), f64.
        local OUT = create(8000)
        -- x faces: along x, p = y, q = z.
        for q = 0, 7 do
          for p = 0, 7 do
            local a = (p + 1) * DY + (q + 1) * DZ
            local wa = readf32(W, a * 4)
            local ma = readu8(M, a)
            local oa = ma == 0 or ma == WATER
            local ua = readu8(M, a - DY)
            local sa = not (ua == 0 or ua == WATER) or readf32(W, (a - DY) * 4) + wa > 1
            local carry = 0
            for s = 1, 9 do
              local b = a + 1
              local wb = readf32(W, b * 4)
              local mb = readu8(M, b)
              local ob = mb == 0 or mb == WATER
              local ub = readu8(M, b - DY)
              local sb = not (ub == 0 or ub == WATER) or readf32(W, (b - DY) * 4) + wb > 1
              local sent, back = 0, 0
              if wa ~= wb and oa and ob then
                local ea = if wa > film then wa - film else 0
                local eb = if wb > film then wb - film else 0
                local f = spread * (ea - eb)
                if f > still then
                  if sa then
                    sent = f
                  end
                elseif f < -still then
                  if sb then
                    back = -f
                  end
                end
              end
              if s > 1 then
                writef64(OUT, a * 8, (carry + sent))
              end
              carry = back
              a, wa, oa, sa = b, wb, ob, sb
            end
          end
        end
        -- z faces: along z, p = x, q = y.
        for q = 0, 7 do
          for p = 0, 7 do
            local a = (p + 1) + (q + 1) * DY
            local wa = readf32(W, a * 4)
            local ma = readu8(M, a)
            local oa = ma == 0 or ma == WATER
            local ua = readu8(M, a - DY)
            local sa = not (ua == 0 or ua == WATER) or readf32(W, (a - DY) * 4) + wa > 1
            local carry = 0
            for s = 1, 9 do
              local b = a + DZ
              local wb = readf32(W, b * 4)
              local mb = readu8(M, b)
              local ob = mb == 0 or mb == WATER
              local ub = readu8(M, b - DY)
              local sb = not (ub == 0 or ub == WATER) or readf32(W, (b - DY) * 4) + wb > 1
              local sent, back = 0, 0
              if wa ~= wb and oa and ob then
                local ea = if wa > film then wa - film else 0
                local eb = if wb > film then wb - film else 0
                local f = spread * (ea - eb)
                if f > still then
                  if sa then
                    sent = f
                  end
                elseif f < -still then
                  if sb then
                    back = -f
                  end
                end
              end
              if s > 1 then
                writef64(OUT, a * 8, readf64(OUT, a * 8) + (carry + sent))
              end
              carry = back
              a, wa, oa, sa = b, wb, ob, sb
            end
          end
        end
        -- vertical faces: along y (a below b), p = x, q = z.
        for q = 0, 7 do
          for p = 0, 7 do
            local a = (p + 1) + (q + 1) * DZ
            local wa = readf32(W, a * 4)
            local ma = readu8(M, a)
            local oa = ma == 0 or ma == WATER
            local carry = 0
            for s = 1, 9 do
              local b = a + DY
              local wb = readf32(W, b * 4)
              local mb = readu8(M, b)
              local ob = mb == 0 or mb == WATER
              local sent, back = 0, 0
              local t = wa + wb
              if t > 0 and oa and ob then
                local f = if t <= 1 then -wb else fall * (wa - lower(t, comp))
                if f > still then
                  sent = f
                elseif f < -still then
                  back = -f
                end
              end
              if s > 1 then
                writef64(OUT, a * 8, readf64(OUT, a * 8) + (carry + sent))
              end
              carry = back
              a, wa, oa = b, wb, ob
            end
          end
        end
        for z = 0, 7 do
          for y = 0, 7 do
            for x = 0, 7 do
              local h = (x + 1) + (y + 1) * DY + (z + 1) * DZ
              local out = readf64(OUT, h * 8)
              local m = readf32(W, h * 4)
              -- k only matters where the cell sends something; 0 elsewhere
              -- keeps the channel sparse (air and water at rest hold none).
              writef32(K, (x + y * 8 + z * 64) * 4, if out == 0 then 0 elseif out > m then m / out else 1)
            end
          end
        end
      end,
    },
    {
      name = "flow",
      reads = { "water", "k" },
      writes = { "water", "mat" },
      kernel = function(c, bx: number, by: number, bz: number)
        local W: buffer, KK: buffer, M: buffer = c.r.water, c.r.k, c.r.mat
        local WO: buffer, MO: buffer = c.w.water, c.w.mat
        local WATER: number = c.m.water
        local comp: number, fall: number, spread: number, still: number =
          c.p.compress, c.p.fall, c.p.spread, c.p.still
        local film: number = c.p.film
        local sum = 2 * spread + 0.5 * fall
        if sum > STABLE then
          local r = STABLE / sum
          spread, fall = spread * r, fall * r
        end
        -- Each cell's change, f64: a face's flux (f > 0: a sends), scaled
        -- by the sender's k, is taken from a and given to b.
        local D = create(8000)
        -- x faces: along x, p = y, q = z.
        for q = 0, 7 do
          for p = 0, 7 do
            local a = (p + 1) * DY + (q + 1) * DZ
            local wa = readf32(W, a * 4)
            local ma = readu8(M, a)
            local oa = ma == 0 or ma == WATER
            local ua = readu8(M, a - DY)
            local sa = not (ua == 0 or ua == WATER) or readf32(W, (a - DY) * 4) + wa > 1
            local carry = 0
            for s = 1, 9 do
              local b = a + 1
              local wb = readf32(W, b * 4)
              local mb = readu8(M, b)
              local ob = mb == 0 or mb == WATER
              local ub = readu8(M, b - DY)
              local sb = not (ub == 0 or ub == WATER) or readf32(W, (b - DY) * 4) + wb > 1
              local g = 0
              if wa ~= wb and oa and ob then
                local ea = if wa > film then wa - film else 0
                local eb = if wb > film then wb - film else 0
                local f = spread * (ea - eb)
                if f > still then
                  if sa then
                    g = f * readf32(KK, a * 4)
                  end
                elseif f < -still then
                  if sb then
                    g = f * readf32(KK, b * 4)
                  end
                end
              end
              if s > 1 then
                writef64(D, a * 8, (carry - g))
              end
              carry = g
              a, wa, oa, sa = b, wb, ob, sb
            end
          end
        end
        -- z faces: along z, p = x, q = y.
        for q = 0, 7 do
          for p = 0, 7 do
            local a = (p + 1) + (q + 1) * DY
            local wa = readf32(W, a * 4)
            local ma = readu8(M, a)
            local oa = ma == 0 or ma == WATER
            local ua = readu8(M, a - DY)
            local sa = not (ua == 0 or ua == WATER) or readf32(W, (a - DY) * 4) + wa > 1
            local carry = 0
            for s = 1, 9 do
              local b = a + DZ
              local wb = readf32(W, b * 4)
              local mb = readu8(M, b)
              local ob = mb == 0 or mb == WATER
              local ub = readu8(M, b - DY)
              local sb = not (ub == 0 or ub == WATER) or readf32(W, (b - DY) * 4) + wb > 1
              local g = 0
              if wa ~= wb and oa and ob then
                local ea = if wa > film then wa - film else 0
                local eb = if wb > film then wb - film else 0
                local f = spread * (ea - eb)
                if f > still then
                  if sa then
                    g = f * readf32(KK, a * 4)
                  end
                elseif f < -still then
                  if sb then
                    g = f * readf32(KK, b * 4)
                  end
                end
              end
              if s > 1 then
                writef64(D, a * 8, readf64(D, a * 8) + (carry - g))
              end
              carry = g
              a, wa, oa, sa = b, wb, ob, sb
            end
          end
        end
        -- vertical faces: along y (a below b), p = x, q = z.
        for q = 0, 7 do
          for p = 0, 7 do
            local a = (p + 1) + (q + 1) * DZ
            local wa = readf32(W, a * 4)
            local ma = readu8(M, a)
            local oa = ma == 0 or ma == WATER
            local carry = 0
            for s = 1, 9 do
              local b = a + DY
              local wb = readf32(W, b * 4)
              local mb = readu8(M, b)
              local ob = mb == 0 or mb == WATER
              local g = 0
              local t = wa + wb
              if t > 0 and oa and ob then
                local f = if t <= 1 then -wb else fall * (wa - lower(t, comp))
                if f > still then
                  g = f * readf32(KK, a * 4)
                elseif f < -still then
                  g = f * readf32(KK, b * 4)
                end
              end
              if s > 1 then
                writef64(D, a * 8, readf64(D, a * 8) + (carry - g))
              end
              carry = g
              a, wa, oa = b, wb, ob
            end
          end
        end
        for z = 0, 7 do
          for y = 0, 7 do
            for x = 0, 7 do
              local h = (x + 1) + (y + 1) * DY + (z + 1) * DZ
              local p = readu8(M, h)
              if p == 0 or p == WATER then
                local i = x + y * 8 + z * 64
                local new = max(readf32(W, h * 4) + readf64(D, h * 8), 0)
                writef32(WO, i * 4, new)
                writeu8(MO, i, if new >= 0.5 then WATER else 0)
              end
            end
          end
        end
      end,
    },
  },
}
