---@meta
-- LuaLS definitions for brickworld simulation scripts (see docs/lua-api.md).

---A 10x10 halo (reads) or 8x8 (writes) array of f64 values; use
---buffer.readf64 / buffer.writef64 with byte offsets:
---halo (x, z) in -1..8: ((z + 1) * 10 + (x + 1)) * 8; own (x, z) in 0..7: (z * 8 + x) * 8.
---@alias brickworld.Field buffer

---@class brickworld.Context
---@field dt number               Seconds this run covers: the world's step, times N for `every = N`.
---@field p table<string, number> Parameter values (read-only).
---@field r table<string, brickworld.Field> Halo buffers of the channels the pass reads (previous generation).
---@field w table<string, brickworld.Field> Output buffers of the channels the pass writes (pre-filled with current values).

---@alias brickworld.Kernel fun(c: brickworld.Context, tx: integer, tz: integer)

---@class brickworld.Pass
---@field name? string    Default: pass1, pass2… by position.
---@field reads? string[]  Channels read with a one-column halo.
---@field writes string[]  Channels written (own tile only).
---@field kernel brickworld.Kernel

---@class brickworld.Param
---@field default number
---@field min number
---@field max number

---@class brickworld.Script
---@field channels string[]                          Every channel the script touches.
---@field nonnegative? string[]                      Channels a step may not drive below zero.
---@field params? table<string, brickworld.Param>    Parameters with defaults and ranges.
---@field passes brickworld.Pass[]                   Run in order each step.
---@field grid? "columns"|"voxels"                  The grid the kernels run over (default "columns").
---@field conserved? string[]                        Channels whose totals are reported (columns) or checked (voxels).
---@field ranges? table<string, number[]>            { min, max } per channel; a step writing outside is rejected.
---@field boundary? table<string, number>            Column scripts: halo value outside the world, per channel.
---@field drains? string[]                           Column scripts: channels the moat removes and counts.
---@field cfl? table                                 Column scripts: { depth, velocities, gravity, dx } for sub-stepping.
---@field materials? string[]                        Voxel scripts: material names the kernel uses.
---@field only? string[]                             Voxel scripts: run only on bricks holding these.
---@field keep_awake? string[]                       Voxel scripts: bricks holding these never sleep.
---@field fills? table<string, string>               Voxel scripts: channel = material, filled in a fresh world.
---@field sky? boolean                               Voxel scripts: run on the top layer of bricks only.
-- Any other key is a load error (see docs/lua-api.md).
