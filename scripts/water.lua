-- Water: the virtual pipe model (Mei, Decaudin & Hu 2007) over columns.
--
-- Each column holds a water depth and four outflow pipes (to -x, +x, -z, +z)
-- that carry momentum from step to step. Pass "flux" accelerates the pipes by
-- the difference in surface height and scales a column's outflow so that it
-- never sends more water than it holds (depth stays non-negative). Pass
-- "apply" moves water: what a column sends through a pipe is exactly what its
-- neighbour receives, so water is conserved to round-off.
--
-- Stable while dt <= C * dx / sqrt(g * h) (gravity-wave CFL); the runtime
-- rejects a step that produces NaN or negative water.
--
-- The native reference (src/sim/native.rs) performs the same arithmetic in
-- the same order; keep them in step.

local readf64, writef64 = buffer.readf64, buffer.writef64
local max = math.max

return {
  channels = { "ground", "water", "out_l", "out_r", "out_b", "out_t" },
  nonnegative = { "water", "out_l", "out_r", "out_b", "out_t" },
  params = {
    gravity = { default = 9.81, min = 0, max = 100 },
    pipe_area = { default = 1, min = 0, max = 10 },
    rain = { default = 0, min = 0, max = 10 },
  },
  passes = {
    {
      name = "flux",
      reads = { "ground", "water", "out_l", "out_r", "out_b", "out_t" },
      writes = { "out_l", "out_r", "out_b", "out_t" },
      kernel = function(c)
        local dt = c.dt
        local k = dt * (c.p.gravity * c.p.pipe_area)
        local r, w = c.r, c.w
        local B, D = r.ground, r.water
        local L, R, Bo, T = r.out_l, r.out_r, r.out_b, r.out_t
        local wl, wr, wb, wt = w.out_l, w.out_r, w.out_b, w.out_t
        for z = 0, 7 do
          for x = 0, 7 do
            local i = ((z + 1) * 10 + x + 1) * 8
            local d = readf64(D, i)
            local h = readf64(B, i) + d
            local fl = max(0, readf64(L, i) + k * (h - (readf64(B, i - 8) + readf64(D, i - 8))))
            local fr = max(0, readf64(R, i) + k * (h - (readf64(B, i + 8) + readf64(D, i + 8))))
            local fb = max(0, readf64(Bo, i) + k * (h - (readf64(B, i - 80) + readf64(D, i - 80))))
            local ft = max(0, readf64(T, i) + k * (h - (readf64(B, i + 80) + readf64(D, i + 80))))
            local sum = fl + fr + fb + ft
            if sum > 0 then
              local s = d / (sum * dt)
              if s < 1 then
                fl = fl * s
                fr = fr * s
                fb = fb * s
                ft = ft * s
              end
            end
            local o = (z * 8 + x) * 8
            writef64(wl, o, fl)
            writef64(wr, o, fr)
            writef64(wb, o, fb)
            writef64(wt, o, ft)
          end
        end
      end,
    },
    {
      name = "apply",
      reads = { "water", "out_l", "out_r", "out_b", "out_t" },
      writes = { "water" },
      kernel = function(c)
        local dt = c.dt
        local rain = c.p.rain
        local r = c.r
        local D = r.water
        local L, R, Bo, T = r.out_l, r.out_r, r.out_b, r.out_t
        local wd = c.w.water
        for z = 0, 7 do
          for x = 0, 7 do
            local i = ((z + 1) * 10 + x + 1) * 8
            local out = readf64(L, i) + readf64(R, i) + readf64(Bo, i) + readf64(T, i)
            local inflow = readf64(R, i - 8) + readf64(L, i + 8) + readf64(T, i - 80) + readf64(Bo, i + 80)
            writef64(wd, (z * 8 + x) * 8, readf64(D, i) + dt * (inflow - out) + rain * dt)
          end
        end
      end,
    },
  },
}
