--!strict
-- rain3d.lua: rain for water3d. Every `every` ticks (set in the world
-- config), each open voxel of the world's top layer gains a drop (a full
-- voxel of water) with chance `rain`; water3d lets it fall one voxel per
-- tick, compact, and then carries it down slopes, into caves and out of
-- them. Drops, not a sheet: a sheet of thin water would wake every brick of
-- sky it falls through, while a drop wakes only the few around it. The
-- draw is c.random(x, y, z): the same storm on any number of threads.
--
-- `sky = true` runs it on the world's top layer of bricks whether they are
-- awake or not (they are empty sky). Rain is a source: it adds water, so
-- it declares nothing conserved; water3d checks its own moves.

local readu8 = buffer.readu8
local readf32, writef32 = buffer.readf32, buffer.writef32

return {
  grid = "voxels",
  sky = true,
  channels = { "water" },
  materials = { "water" },
  params = {
    -- Chance of a drop per top voxel per run (its expected fill).
    rain = { default = 0.001, min = 0.0, max = 1.0 },
  },
  passes = {
    {
      name = "rain",
      reads = {},
      writes = { "water" },
      kernel = function(c, bx: number, by: number, bz: number)
        local r, w = c.r.mat, c.w.water
        local WATER, rain = c.m.water, c.p.rain
        if rain <= 0 then
          return
        end
        -- Only the topmost voxel row of the world: above it is the wall (255).
        for z = 0, 7 do
          for x = 0, 7 do
            for y = 7, 0, -1 do
              local h = (x + 1) + (y + 1) * 10 + (z + 1) * 100
              if readu8(r, h + 10) == 255 then
                local m = readu8(r, h)
                if (m == 0 or m == WATER) and c.random(bx * 8 + x, by * 8 + y, bz * 8 + z) < rain then
                  local i = (x + y * 8 + z * 64) * 4
                  writef32(w, i, readf32(w, i) + 1)
                end
                break
              end
            end
          end
        end
      end,
    },
  },
}
