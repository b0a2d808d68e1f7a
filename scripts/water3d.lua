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
-- thread count:
--   limit: each cell sums what it would send through its six faces and
--          stores k = min(1, fill / outflow), so it never sends more than
--          it holds;
--   flow:  each face's flux is computed from the two cells' fills (the same
--          formula on both sides), scaled by the sender's k, and applied to
--          both cells. A cell is drawn as water when it is at least half full.
--
-- Faces into solid cells (anything but air and water, and the world's
-- boundary) carry nothing. Fluxes below `still` are dropped on both sides
-- alike, so water at rest stops changing exactly and its bricks sleep.

local readf32, writef32 = buffer.readf32, buffer.writef32
local readu8, writeu8 = buffer.readu8, buffer.writeu8
local min, max = math.min, math.max

-- Halo strides (x fastest, then y, then z, 10 per axis).
local DY, DZ = 10, 100
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

-- The four sideways neighbours' halo offsets (read only).
local SIDES = table.freeze({ 1, -1, DZ, -DZ })

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
    fall = { default = 0.5, min = 0.0, max = 1.0 },
    spread = { default = 0.2, min = 0.0, max = 0.5 },
    still = { default = 1e-5, min = 0.0, max = 0.01 },
  },
  passes = {
    {
      name = "limit",
      reads = { "water" },
      writes = { "k" },
      kernel = function(c, bx: number, by: number, bz: number)
        local W, M, K = c.r.water, c.r.mat, c.w.k
        local WATER = c.m.water
        local comp, fall, spread, still = c.p.compress, c.p.fall, c.p.spread, c.p.still
        local function open(h: number): boolean
          local m = readu8(M, h)
          return m == 0 or m == WATER
        end
        -- The fill the lower of two stacked cells holds at rest, given their total.
        for z = 0, 7 do
          for y = 0, 7 do
            for x = 0, 7 do
              local h = (x + 1) + (y + 1) * DY + (z + 1) * DZ
              local i = x + y * 8 + z * 64
              local m = readf32(W, h * 4)
              local out = 0
              if m > 0 and open(h) then
                -- down
                if open(h - DY) then
                  local b = readf32(W, (h - DY) * 4)
                  local f = fall * (lower(m + b, comp) - b)
                  if f > still then out += f end
                end
                -- up (only when compressed)
                if open(h + DY) then
                  local a = readf32(W, (h + DY) * 4)
                  local f = -fall * (lower(m + a, comp) - m)
                  if f > still then out += f end
                end
                -- sideways
                for _, d in SIDES do
                  if open(h + d) then
                    local f = spread * (m - readf32(W, (h + d) * 4))
                    if f > still then out += f end
                  end
                end
              end
              writef32(K, i * 4, if out > m then m / out else 1)
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
        local W, KK, M = c.r.water, c.r.k, c.r.mat
        local WO, MO = c.w.water, c.w.mat
        local WATER = c.m.water
        local comp, fall, spread, still = c.p.compress, c.p.fall, c.p.spread, c.p.still
        local function open(h: number): boolean
          local m = readu8(M, h)
          return m == 0 or m == WATER
        end
        -- The flux from cell a to cell b (fills ma, mb), already scaled by
        -- the sender's k; `dir` is DY when b is below a, -DY above, 0 sideways.
        local function flux(ha: number, hb: number, ma: number, mb: number, dir: number): number
          local f
          if dir == DY then
            f = fall * (lower(ma + mb, comp) - mb)
          elseif dir == -DY then
            f = -fall * (lower(ma + mb, comp) - ma)
          else
            f = spread * (ma - mb)
          end
          if f > still then
            return f * readf32(KK, ha * 4)
          elseif f < -still then
            return f * readf32(KK, hb * 4)
          end
          return 0
        end
        for z = 0, 7 do
          for y = 0, 7 do
            for x = 0, 7 do
              local h = (x + 1) + (y + 1) * DY + (z + 1) * DZ
              local i = x + y * 8 + z * 64
              if open(h) then
                local m = readf32(W, h * 4)
                local new = m
                if open(h - DY) then new -= flux(h, h - DY, m, readf32(W, (h - DY) * 4), DY) end
                if open(h + DY) then new -= flux(h, h + DY, m, readf32(W, (h + DY) * 4), -DY) end
                for _, d in SIDES do
                  if open(h + d) then new -= flux(h, h + d, m, readf32(W, (h + d) * 4), 0) end
                end
                new = max(new, 0)
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
