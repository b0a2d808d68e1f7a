--!strict
-- lava.lua: a viscous flow from a source that cools to basalt where it
-- touches water.
--
-- * A `lava_source` voxel pours lava into the air below it every tick
--   (and counts each voxel it pours in its `poured` channel).
-- * Lava falls straight down into air. Resting lava flows one voxel sideways
--   into air with probability `flow` per tick (its viscosity), in the one
--   direction of this tick (it turns with the tick).
-- * Lava with water among its six neighbours cools to basalt.
--
-- Moves use sand's pattern: the source and its target evaluate the same
-- conditions (the chance is drawn for the source's position, so both sides
-- draw the same number), so lava is never lost or duplicated. The rule that
-- verification checks: lava + basalt made = lava at the start + poured.

local readu8, writeu8 = buffer.readu8, buffer.writeu8
local readf32, writef32 = buffer.readf32, buffer.writef32

local DIRS = table.freeze({ { 1, 0 }, { 0, 1 }, { -1, 0 }, { 0, -1 } })

return {
  grid = "voxels",
  channels = { "poured" },
  materials = { "lava", "lava_source", "basalt", "water" },
  only = { "lava", "lava_source" },
  keep_awake = { "lava_source" },
  params = {
    flow = { default = 0.25, min = 0.0, max = 1.0 },
  },
  passes = {
    {
      -- Lava with water among its six neighbours cools to basalt.
      name = "cool",
      reads = {},
      writes = { "mat" },
      kernel = function(c, bx: number, by: number, bz: number)
        local r, w = c.r.mat, c.w.mat
        local LAVA, BASALT, WATER = c.m.lava, c.m.basalt, c.m.water
        for z = 0, 7 do
          for y = 0, 7 do
            for x = 0, 7 do
              local h = (x + 1) + (y + 1) * 10 + (z + 1) * 100
              if readu8(r, h) == LAVA
                and (readu8(r, h - 1) == WATER or readu8(r, h + 1) == WATER
                  or readu8(r, h - 10) == WATER or readu8(r, h + 10) == WATER
                  or readu8(r, h - 100) == WATER or readu8(r, h + 100) == WATER)
              then
                writeu8(w, x + y * 8 + z * 64, BASALT)
              end
            end
          end
        end
      end,
    },
    {
      name = "flow",
      reads = { "poured" },
      writes = { "mat", "poured" },
      kernel = function(c, bx: number, by: number, bz: number)
        local r, w = c.r.mat, c.w.mat
        local P = c.w.poured
        local LAVA, SOURCE = c.m.lava, c.m.lava_source
        local flow = c.p.flow
        local d = DIRS[c.tick % 4 + 1]
        local dx, dz = d[1], d[2]
        local ox, oy, oz = bx * 8, by * 8, bz * 8
        -- Whether the resting lava at halo cell h (world voxel x, y, z)
        -- flows sideways this tick. Source and target both ask this, with
        -- the source's position, so they agree.
        local function slides(h: number, x: number, y: number, z: number): boolean
          local t = h + dx + dz * 100
          return readu8(r, h - 10) ~= 0
            and readu8(r, t) == 0
            and readu8(r, t + 10) ~= LAVA
            and readu8(r, t + 10) ~= SOURCE
            and c.random(x, y, z) < flow
        end
        for z = 0, 7 do
          for y = 0, 7 do
            for x = 0, 7 do
              local h = (x + 1) + (y + 1) * 10 + (z + 1) * 100
              local i = x + y * 8 + z * 64
              local m = readu8(r, h)
              if m == LAVA then
                if readu8(r, h - 10) == 0 or slides(h, ox + x, oy + y, oz + z) then
                  writeu8(w, i, 0)
                end
              elseif m == SOURCE then
                if readu8(r, h - 10) == 0 then
                  writef32(P, i * 4, readf32(P, i * 4) + 1)
                end
              elseif m == 0 then
                local above = readu8(r, h + 10)
                if above == LAVA or above == SOURCE then
                  writeu8(w, i, LAVA)
                elseif readu8(r, h - dx - dz * 100) == LAVA
                  and slides(h - dx - dz * 100, ox + x - dx, oy + y, oz + z - dz)
                then
                  writeu8(w, i, LAVA)
                end
              end
            end
          end
        end
      end,
    },
  },
}
