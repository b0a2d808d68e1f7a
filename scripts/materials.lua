-- materials.lua: the materials the shipped voxel scripts use. Add your own
-- here: a name, a colour, a kind (solid, liquid, granular or gas) and a
-- density relative to water. Ids are given by the engine and stay the same
-- for a world's whole life, across hot reloads and restarts (a restart frees
-- the ids of names no file declares and no voxel holds once few are left).
return {
  sand = { color = { 218, 196, 140 }, kind = "granular", density = 1.6 },
  lava = { color = { 255, 96, 24 }, kind = "liquid", density = 3.1 },
  lava_source = { color = { 255, 160, 60 }, kind = "solid", density = 3.1 },
  basalt = { color = { 58, 54, 56 }, kind = "solid", density = 2.9 },
  steam = { color = { 226, 232, 240 }, kind = "gas", density = 0.0006 },
}
