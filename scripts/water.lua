-- Water: shallow-water flow on a staggered grid of columns (after Stelling &
-- Duinmeijer 2003), carrying momentum, conserving mass to round-off.
--
-- Each column of side dx holds a depth h. Velocities live on faces: u on a
-- column's +x face, v on its +z face; they carry momentum from step to step.
--
--   1. "momentum": u += -dt * ADV - g dt d(eta)/dx, eta = ground + h, with
--      the momentum-conservative upwind advection of Stelling & Duinmeijer:
--      ADV = [(qc_r u*_r - qc_l u*_l) - u (qc_r - qc_l)] / (dx hbar), where
--      qc are cell-centred discharges (mean of the two faces' q from the last
--      step) and u* the upwind face velocities; this carries momentum across
--      wet/dry fronts, which the plain u du/dx form does not. A face whose
--      hydrostatic depth
--      max(eta_i, eta_j) - max(b_i, b_j) is zero is dry and stops (u = 0), so
--      a lake at rest stays exactly at rest (well-balanced) and dry ground
--      never moves water.
--      Bed friction (quadratic, implicit): u /= 1 + dt cf |u| / max(hbar, 0.01).
--   2. "flux": the discharge through each face, q = u * h_upwind * K, is
--      computed once, by the face's owner. K = min(1, dx / (dt * sum of the
--      upwind column's outflow speeds)) keeps every column from sending more
--      water than it holds, so depth never goes negative.
--   3. "continuity": h += dt/dx * (q_in - q_out) + rain * dt, using the same q
--      on both sides of every face: water is conserved to round-off.
--
-- Stable while dt * (|u| + sqrt(g h)) / dx stays below about 1 (CFL); the
-- runtime rejects a step that writes NaN or negative depth.
--
-- The native reference (src/sim/columns/native.rs) performs the same arithmetic in
-- the same order; keep them in step.

local readf64, writef64 = buffer.readf64, buffer.writef64
local max = math.max

return {
  channels = { "ground", "water", "u", "v", "qx", "qz" },
  nonnegative = { "water" },
  -- A discharge is depth times speed: a channel 40 deep flowing at 10 per
  -- second carries 400, past the default bound of 4 world heights, which
  -- suspended water under heavy rain. Runaway values are still caught.
  ranges = { qx = { -1e6, 1e6 }, qz = { -1e6, 1e6 } },
  -- Outside the world the ground is a wall; water leaves over the edges
  -- (into the moat) and the runtime sub-steps to keep this CFL limit.
  boundary = { ground = 1e9 },
  drains = { "water" },
  cfl = { depth = "water", velocities = { "u", "v" }, gravity = "gravity", dx = "dx" },
  params = {
    gravity = { default = 9.81, min = 0, max = 100 },
    dx = { default = 1, min = 0.001, max = 1000 },
    rain = { default = 0, min = 0, max = 10 },
    friction = { default = 0.02, min = 0, max = 10 },
  },
  passes = {
    {
      name = "momentum",
      reads = { "ground", "water", "u", "v", "qx", "qz" },
      writes = { "u", "v" },
      kernel = function(c)
        local dt, g, dx = c.dt, c.p.gravity, c.p.dx
        local r = c.r
        local B, H, U, V, QX, QZ = r.ground, r.water, r.u, r.v, r.qx, r.qz
        local wu, wv = c.w.u, c.w.v
        local k = g * dt / dx
        local cf = c.p.friction * dt
        local abs = math.abs
        -- Advection of the face velocity f at offset i along a step of s bytes
        -- (8 for x, 80 for z), from face velocities F and discharges Q.
        local function adv(F, Q, i, s, f, hbar)
          local ql = (readf64(Q, i - s) + readf64(Q, i)) * 0.5
          local qr = (readf64(Q, i) + readf64(Q, i + s)) * 0.5
          local ul = f
          if ql >= 0 then
            ul = readf64(F, i - s)
          end
          local ur = readf64(F, i + s)
          if qr >= 0 then
            ur = f
          end
          return ((qr * ur - ql * ul) - f * (qr - ql)) / (dx * hbar)
        end
        for z = 0, 7 do
          for x = 0, 7 do
            local i = ((z + 1) * 10 + x + 1) * 8
            local o = (z * 8 + x) * 8
            local b = readf64(B, i)
            local h = readf64(H, i)
            local e = b + h
            -- +x face
            local br = readf64(B, i + 8)
            local hr = readf64(H, i + 8)
            local er = br + hr
            local nu = 0
            if max(e, er) - max(b, br) > 1e-9 then
              local u = readf64(U, i)
              local hbar = (h + hr) * 0.5
              local a = 0
              if hbar > 1e-9 then
                a = adv(U, QX, i, 8, u, hbar)
              end
              nu = u - dt * a - k * (er - e)
              nu = nu / (1 + cf * abs(nu) / max(hbar, 0.01))
            end
            writef64(wu, o, nu)
            -- +z face
            local bt = readf64(B, i + 80)
            local ht = readf64(H, i + 80)
            local et = bt + ht
            local nv = 0
            if max(e, et) - max(b, bt) > 1e-9 then
              local v = readf64(V, i)
              local hbar = (h + ht) * 0.5
              local a = 0
              if hbar > 1e-9 then
                a = adv(V, QZ, i, 80, v, hbar)
              end
              nv = v - dt * a - k * (et - e)
              nv = nv / (1 + cf * abs(nv) / max(hbar, 0.01))
            end
            writef64(wv, o, nv)
          end
        end
      end,
    },
    {
      name = "flux",
      reads = { "water", "u", "v" },
      writes = { "qx", "qz" },
      kernel = function(c)
        local dt, dx = c.dt, c.p.dx
        local r = c.r
        local H, U, V = r.water, r.u, r.v
        local wx, wz = c.w.qx, c.w.qz
        -- Outflow limiter of the column at halo offset j.
        local function lim(j)
          local s = max(0, readf64(U, j)) + max(0, -readf64(U, j - 8)) + max(0, readf64(V, j)) + max(0, -readf64(V, j - 80))
          local t = s * dt
          if t > dx then
            return dx / t
          end
          return 1
        end
        for z = 0, 7 do
          for x = 0, 7 do
            local i = ((z + 1) * 10 + x + 1) * 8
            local o = (z * 8 + x) * 8
            local u = readf64(U, i)
            local v = readf64(V, i)
            -- The own column's limiter, computed once if either face needs it.
            local own = 1
            if u > 0 or v > 0 then
              own = lim(i)
            end
            local qx = 0
            if u > 0 then
              qx = u * readf64(H, i) * own
            elseif u < 0 then
              qx = u * readf64(H, i + 8) * lim(i + 8)
            end
            writef64(wx, o, qx)
            local qz = 0
            if v > 0 then
              qz = v * readf64(H, i) * own
            elseif v < 0 then
              qz = v * readf64(H, i + 80) * lim(i + 80)
            end
            writef64(wz, o, qz)
          end
        end
      end,
    },
    {
      name = "continuity",
      reads = { "water", "qx", "qz" },
      writes = { "water" },
      kernel = function(c)
        local a = c.dt / c.p.dx
        local rain = c.p.rain * c.dt
        local r = c.r
        local H, QX, QZ = r.water, r.qx, r.qz
        local w = c.w.water
        for z = 0, 7 do
          for x = 0, 7 do
            local i = ((z + 1) * 10 + x + 1) * 8
            local net = (readf64(QX, i - 8) - readf64(QX, i)) + (readf64(QZ, i - 80) - readf64(QZ, i))
            writef64(w, (z * 8 + x) * 8, readf64(H, i) + a * net + rain)
          end
        end
      end,
    },
  },
}
