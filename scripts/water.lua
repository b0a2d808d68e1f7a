-- Water: the virtual pipe model (Mei, Decaudin & Hu 2007) over columns.
--
-- Each column (side dx) holds a water depth and four outflow pipes (to -x,
-- +x, -z, +z) that carry momentum from step to step. Pass "flux" accelerates
-- each pipe by g * A * (surface drop) / dx, with the pipe's cross-section
-- A = h_face * dx and h_face = max(eta_i, eta_j) - max(b_i, b_j) (the
-- hydrostatic face depth): gravity waves then travel at sqrt(g h) as in the
-- shallow-water equations, a lake at rest stays exactly at rest, and a dry
-- column never sends water. The column's outflow is then scaled so that it
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
    dx = { default = 1, min = 0.001, max = 1000 },
    rain = { default = 0, min = 0, max = 10 },
  },
  passes = {
    {
      name = "flux",
      reads = { "ground", "water", "out_l", "out_r", "out_b", "out_t" },
      writes = { "out_l", "out_r", "out_b", "out_t" },
      kernel = function(c)
        local dt = c.dt
        local k = dt * c.p.gravity
        local r, w = c.r, c.w
        local B, D = r.ground, r.water
        local L, R, Bo, T = r.out_l, r.out_r, r.out_b, r.out_t
        local wl, wr, wb, wt = w.out_l, w.out_r, w.out_b, w.out_t
        for z = 0, 7 do
          for x = 0, 7 do
            local i = ((z + 1) * 10 + x + 1) * 8
            local d = readf64(D, i)
            local b = readf64(B, i)
            local h = b + d
            local bl, br, bb, bt = readf64(B, i - 8), readf64(B, i + 8), readf64(B, i - 80), readf64(B, i + 80)
            local hl, hr, hb, ht = bl + readf64(D, i - 8), br + readf64(D, i + 8), bb + readf64(D, i - 80), bt + readf64(D, i + 80)
            local fl = max(0, readf64(L, i) + k * (max(h, hl) - max(b, bl)) * (h - hl))
            local fr = max(0, readf64(R, i) + k * (max(h, hr) - max(b, br)) * (h - hr))
            local fb = max(0, readf64(Bo, i) + k * (max(h, hb) - max(b, bb)) * (h - hb))
            local ft = max(0, readf64(T, i) + k * (max(h, ht) - max(b, bt)) * (h - ht))
            local sum = fl + fr + fb + ft
            if sum > 0 then
              local s = d * (c.p.dx * c.p.dx) / (sum * dt)
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
        local area = c.p.dx * c.p.dx
        for z = 0, 7 do
          for x = 0, 7 do
            local i = ((z + 1) * 10 + x + 1) * 8
            local out = readf64(L, i) + readf64(R, i) + readf64(Bo, i) + readf64(T, i)
            local inflow = readf64(R, i - 8) + readf64(L, i + 8) + readf64(T, i - 80) + readf64(Bo, i + 80)
            writef64(wd, (z * 8 + x) * 8, readf64(D, i) + dt * (inflow - out) / area + rain * dt)
          end
        end
      end,
    },
  },
}
