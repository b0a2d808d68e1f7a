-- Snow (after Fearing 2000): snow falls, accumulates, and snow on unstable
-- spots slides to lower neighbours until every slope of the snow surface is
-- at or below the snow's angle of repose. Sliding is in flux form (amounts
-- per face written first, then applied), so snow is conserved to round-off;
-- two slide iterations run per step, and steps repeat until movement is small.
-- `melt` takes that share of the snow away each second (after it falls), so
-- a world under steady snowfall tends to `snowfall / melt` of snow instead
-- of burying itself; at 0 (the default) snow only accumulates.

local readf64, writef64 = buffer.readf64, buffer.writef64
local max, min = math.max, math.min

local function slide_flux(c)
  local repose, rate = c.p.repose, c.p.slide_rate
  local r = c.r
  local G, S = r.ground, r.snow
  local wl, wr, wb, wt = c.w.snw_l, c.w.snw_r, c.w.snw_b, c.w.snw_t
  for z = 0, 7 do
    for x = 0, 7 do
      local i = ((z + 1) * 10 + x + 1) * 8
      local o = (z * 8 + x) * 8
      local s = readf64(S, i)
      local h = readf64(G, i) + s
      local el = max(0, h - (readf64(G, i - 8) + readf64(S, i - 8)) - repose)
      local er = max(0, h - (readf64(G, i + 8) + readf64(S, i + 8)) - repose)
      local eb = max(0, h - (readf64(G, i - 80) + readf64(S, i - 80)) - repose)
      local et = max(0, h - (readf64(G, i + 80) + readf64(S, i + 80)) - repose)
      local total = el + er + eb + et
      local k = 0
      if total > 0 and s > 0 then
        -- Move a share of the largest excess, never more snow than there is.
        k = min(rate * max(el, er, eb, et), s) / total
      end
      writef64(wl, o, el * k)
      writef64(wr, o, er * k)
      writef64(wb, o, eb * k)
      writef64(wt, o, et * k)
    end
  end
end

local function slide_apply(c)
  local r = c.r
  local S = r.snow
  local L, R, Bo, T = r.snw_l, r.snw_r, r.snw_b, r.snw_t
  local w = c.w.snow
  for z = 0, 7 do
    for x = 0, 7 do
      local i = ((z + 1) * 10 + x + 1) * 8
      local out = readf64(L, i) + readf64(R, i) + readf64(Bo, i) + readf64(T, i)
      local inflow = readf64(R, i - 8) + readf64(L, i + 8) + readf64(T, i - 80) + readf64(Bo, i + 80)
      writef64(w, (z * 8 + x) * 8, readf64(S, i) - out + inflow)
    end
  end
end

local slide_reads = { "ground", "snow" }
local slide_writes = { "snw_l", "snw_r", "snw_b", "snw_t" }
local apply_reads = { "snow", "snw_l", "snw_r", "snw_b", "snw_t" }

return {
  channels = { "ground", "snow", "snw_l", "snw_r", "snw_b", "snw_t" },
  nonnegative = { "snow", "snw_l", "snw_r", "snw_b", "snw_t" },
  boundary = { ground = 1e9 }, -- outside the world the ground is a wall
  params = {
    snowfall = { default = 0.0, min = 0, max = 10 },
    melt = { default = 0.0, min = 0, max = 10 },
    repose = { default = 0.8, min = 0.05, max = 10 },
    slide_rate = { default = 0.2, min = 0, max = 0.49 },
  },
  passes = {
    {
      name = "fall",
      reads = {},
      writes = { "snow" },
      kernel = function(c)
        local add = c.p.snowfall * c.dt
        -- What is left after melting (1 without melt: no change at all).
        local keep = 1 - min(1, c.p.melt * c.dt)
        if add > 0 or keep < 1 then
          local w = c.w.snow
          for o = 0, 63 * 8, 8 do
            writef64(w, o, (readf64(w, o) + add) * keep)
          end
        end
      end,
    },
    { name = "slide_flux", reads = slide_reads, writes = slide_writes, kernel = slide_flux },
    { name = "slide_apply", reads = apply_reads, writes = { "snow" }, kernel = slide_apply },
    { name = "slide_flux2", reads = slide_reads, writes = slide_writes, kernel = slide_flux },
    { name = "slide_apply2", reads = apply_reads, writes = { "snow" }, kernel = slide_apply },
  },
}
