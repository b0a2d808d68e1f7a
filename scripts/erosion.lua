-- Erosion: hydraulic erosion with sediment transport in flux form, plus
-- thermal erosion to a talus slope. Runs after water.lua and reads its
-- depths, face velocities (u, v) and face discharges (qx, qz); set `dx` to
-- the same cell size as water.lua's.
--
-- Conservation: every pass that moves material first writes, per column,
-- the amount leaving through each of its four faces (channels ero_*), then
-- an apply pass subtracts a column's own amounts and adds what its
-- neighbours sent towards it. Each amount is computed once and used on both
-- sides, so ground + sediment is conserved to round-off (no semi-Lagrangian
-- advection, which leaks mass).

local readf64, writef64 = buffer.readf64, buffer.writef64
local max, min, sqrt = math.max, math.min, math.sqrt

local function moves_apply(c, src, dst)
  -- dst = src - (own outflows) + (neighbours' outflows towards this column)
  local r = c.r
  local S = r[src]
  local L, R, Bo, T = r.ero_l, r.ero_r, r.ero_b, r.ero_t
  local w = c.w[dst]
  for z = 0, 7 do
    for x = 0, 7 do
      local i = ((z + 1) * 10 + x + 1) * 8
      local out = readf64(L, i) + readf64(R, i) + readf64(Bo, i) + readf64(T, i)
      local inflow = readf64(R, i - 8) + readf64(L, i + 8) + readf64(T, i - 80) + readf64(Bo, i + 80)
      writef64(w, (z * 8 + x) * 8, readf64(S, i) - out + inflow)
    end
  end
end

return {
  channels = { "ground", "water", "sediment", "u", "v", "qx", "qz", "ero_l", "ero_r", "ero_b", "ero_t" },
  nonnegative = { "sediment", "ero_l", "ero_r", "ero_b", "ero_t" },
  boundary = { ground = 1e9 }, -- outside the world the ground is a wall
  params = {
    capacity = { default = 0.05, min = 0, max = 10 },
    dissolve = { default = 0.3, min = 0, max = 10 },
    deposit = { default = 0.3, min = 0, max = 10 },
    talus = { default = 1.2, min = 0.05, max = 10 },
    thermal_rate = { default = 0.2, min = 0, max = 0.49 },
    dx = { default = 1, min = 0.001, max = 1000 },
  },
  passes = {
    {
      -- Local exchange between ground and suspended sediment.
      name = "erode",
      reads = { "ground", "water", "sediment", "u", "v" },
      writes = { "ground", "sediment" },
      kernel = function(c)
        local dt, p = c.dt, c.p
        local r = c.r
        local G, D, S, U, V = r.ground, r.water, r.sediment, r.u, r.v
        local wg, ws = c.w.ground, c.w.sediment
        local inv2dx = 0.5 / p.dx
        for z = 0, 7 do
          for x = 0, 7 do
            local i = ((z + 1) * 10 + x + 1) * 8
            local o = (z * 8 + x) * 8
            local g, s, d = readf64(G, i), readf64(S, i), readf64(D, i)
            if d > 1e-4 then
              local vx = (readf64(U, i) + readf64(U, i - 8)) * 0.5
              local vz = (readf64(V, i) + readf64(V, i - 80)) * 0.5
              local gx = (readf64(G, i + 8) - readf64(G, i - 8)) * inv2dx
              local gz = (readf64(G, i + 80) - readf64(G, i - 80)) * inv2dx
              local slope = sqrt(gx * gx + gz * gz)
              local sin = slope / sqrt(1 + slope * slope)
              local cap = p.capacity * sqrt(vx * vx + vz * vz) * max(sin, 0.05)
              local a
              if s < cap then
                -- Ground below 0 (the moat around a world whose edge is
                -- at height 0 or 1) has nothing to dissolve: a negative
                -- amount drove sediment below 0 and failed the step.
                a = min(p.dissolve * (cap - s) * dt, max(g, 0))
              else
                a = -min(p.deposit * (s - cap) * dt, s)
              end
              writef64(wg, o, g - a)
              writef64(ws, o, s + a)
            end
          end
        end
      end,
    },
    {
      -- Sediment leaves with the water: through each face, the share of the
      -- column's water (before this step's move) that the face carried out.
      name = "transport_flux",
      reads = { "water", "sediment", "qx", "qz" },
      writes = { "ero_l", "ero_r", "ero_b", "ero_t" },
      kernel = function(c)
        local a = c.dt / c.p.dx
        local r = c.r
        local D, S, QX, QZ = r.water, r.sediment, r.qx, r.qz
        local wl, wr, wb, wt = c.w.ero_l, c.w.ero_r, c.w.ero_b, c.w.ero_t
        for z = 0, 7 do
          for x = 0, 7 do
            local i = ((z + 1) * 10 + x + 1) * 8
            local o = (z * 8 + x) * 8
            local qr, ql = readf64(QX, i), readf64(QX, i - 8)
            local qt, qb = readf64(QZ, i), readf64(QZ, i - 80)
            local fr, fl, ft, fb = a * max(0, qr), a * max(0, -ql), a * max(0, qt), a * max(0, -qb)
            local out = fr + fl + ft + fb
            local inflow = a * (max(0, ql) + max(0, -qr) + max(0, qb) + max(0, -qt))
            local before = readf64(D, i) + out - inflow
            local s = readf64(S, i)
            local k = 0
            if out > 0 and before > 1e-9 then
              k = s / before
              if out * k > s then
                k = s / out
              end
            end
            writef64(wl, o, fl * k)
            writef64(wr, o, fr * k)
            writef64(wb, o, fb * k)
            writef64(wt, o, ft * k)
          end
        end
      end,
    },
    {
      name = "transport_apply",
      reads = { "sediment", "ero_l", "ero_r", "ero_b", "ero_t" },
      writes = { "sediment" },
      kernel = function(c)
        moves_apply(c, "sediment", "sediment")
      end,
    },
    {
      -- Thermal erosion: ground above the talus slope slides to lower
      -- neighbours, in proportion to the excess, at most thermal_rate of
      -- the largest excess (kept below 0.5 to avoid oscillation).
      name = "thermal_flux",
      reads = { "ground" },
      writes = { "ero_l", "ero_r", "ero_b", "ero_t" },
      kernel = function(c)
        local talus, rate = c.p.talus, c.p.thermal_rate
        local G = c.r.ground
        local wl, wr, wb, wt = c.w.ero_l, c.w.ero_r, c.w.ero_b, c.w.ero_t
        for z = 0, 7 do
          for x = 0, 7 do
            local i = ((z + 1) * 10 + x + 1) * 8
            local o = (z * 8 + x) * 8
            local g = readf64(G, i)
            local el = max(0, g - readf64(G, i - 8) - talus)
            local er = max(0, g - readf64(G, i + 8) - talus)
            local eb = max(0, g - readf64(G, i - 80) - talus)
            local et = max(0, g - readf64(G, i + 80) - talus)
            local total = el + er + eb + et
            local k = 0
            if total > 0 then
              k = rate * max(el, er, eb, et) / total
            end
            writef64(wl, o, el * k)
            writef64(wr, o, er * k)
            writef64(wb, o, eb * k)
            writef64(wt, o, et * k)
          end
        end
      end,
    },
    {
      name = "thermal_apply",
      reads = { "ground", "ero_l", "ero_r", "ero_b", "ero_t" },
      writes = { "ground" },
      kernel = function(c)
        moves_apply(c, "ground", "ground")
      end,
    },
  },
}
