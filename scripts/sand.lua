--!strict
-- sand.lua: falling granular material that piles to its angle of repose.
--
-- A voxel rule over the raw bricks (grid = "voxels"). Each tick, sand falls
-- straight down into air, or, when it rests on something, slides one voxel
-- diagonally down in one of four directions (the direction turns with the
-- tick), so piles settle at 45 degrees.
--
-- The pattern to copy for anything discrete that moves: every cell decides
-- its own next state from the previous generation, and a source and its
-- target evaluate the *same* conditions, so exactly one of each pair of
-- decisions says "leave" and the other "arrive": grains are never lost or
-- duplicated, whatever order or thread the bricks run in. Competition is
-- ruled out by construction: a target can only be reached from straight
-- above (which wins) or from the one diagonal of this tick's direction.

local readu8, writeu8 = buffer.readu8, buffer.writeu8

-- The four slide directions (read only: kernels keep no state).
local DIRS = table.freeze({ { 1, 0 }, { 0, 1 }, { -1, 0 }, { 0, -1 } })

return {
  grid = "voxels",
  materials = { "sand" },
  only = { "sand" },
  passes = {
    {
      name = "fall",
      reads = {},
      writes = { "mat" },
      kernel = function(c, bx: number, by: number, bz: number)
        local r, w = c.r.mat, c.w.mat
        local SAND = c.m.sand
        local d = DIRS[c.tick % 4 + 1]
        local dx, dz = d[1], d[2]
        for z = 0, 7 do
          for y = 0, 7 do
            for x = 0, 7 do
              local h = (x + 1) + (y + 1) * 10 + (z + 1) * 100
              local m = readu8(r, h)
              local i = x + y * 8 + z * 64
              if m == SAND then
                if readu8(r, h - 10) == 0 then
                  writeu8(w, i, 0) -- falls
                elseif readu8(r, h + dx - 10 + dz * 100) == 0 and readu8(r, h + dx + dz * 100) == 0 then
                  writeu8(w, i, 0) -- slides
                end
              elseif m == 0 then
                if readu8(r, h + 10) == SAND then
                  writeu8(w, i, SAND) -- from straight above
                elseif readu8(r, h + 10) == 0
                  and readu8(r, h - dx + 10 - dz * 100) == SAND
                  and readu8(r, h - dx - dz * 100) ~= 0
                then
                  writeu8(w, i, SAND) -- slid in from the diagonal
                end
              end
            end
          end
        end
      end,
    },
  },
}
