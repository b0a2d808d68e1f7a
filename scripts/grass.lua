--!strict
-- grass.lua: grass spreads to dirt that lies open to the air, by chance.
--
-- A dirt voxel with air above it and grass among its 26 neighbours turns to
-- grass with probability `rate` per tick. The draw is c.random(x, y, z):
-- a pure function of (world seed, tick, script, voxel), so the same world
-- grows the same lawn on any number of threads and across restarts.
--
-- A chance rule must not be starved by sleeping bricks (a brick sleeps when
-- nothing in it changed, which is most ticks for a rare event): bricks that
-- hold dirt are kept awake (`keep_awake`), and the rule only runs where
-- grass is (`only`), which the engine finds without scanning.

local readu8, writeu8 = buffer.readu8, buffer.writeu8

return {
  grid = "voxels",
  materials = { "grass", "dirt" },
  only = { "grass" },
  keep_awake = { "dirt" },
  params = {
    rate = { default = 0.001, min = 0.0, max = 1.0 },
  },
  passes = {
    {
      name = "spread",
      reads = {},
      writes = { "mat" },
      kernel = function(c, bx: number, by: number, bz: number)
        local r, w = c.r.mat, c.w.mat
        local GRASS, DIRT = c.m.grass, c.m.dirt
        local rate = c.p.rate
        for z = 0, 7 do
          for y = 0, 7 do
            for x = 0, 7 do
              local h = (x + 1) + (y + 1) * 10 + (z + 1) * 100
              if readu8(r, h) == DIRT and readu8(r, h + 10) == 0 then
                local near = false
                for dz = -100, 100, 100 do
                  for dy = -10, 10, 10 do
                    for dx = -1, 1 do
                      if readu8(r, h + dx + dy + dz) == GRASS then
                        near = true
                      end
                    end
                  end
                end
                if near and c.random(bx * 8 + x, by * 8 + y, bz * 8 + z) < rate then
                  writeu8(w, x + y * 8 + z * 64, GRASS)
                end
              end
            end
          end
        end
      end,
    },
  },
}
