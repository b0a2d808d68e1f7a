//! Writing simulation columns back into bricks (placeholder until the voxel
//! sync lands: see the issue note).
