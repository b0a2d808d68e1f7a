//! The material registry: named materials (colour, kind, density) with
//! stable 8-bit ids, shared by scenes, scripts, checkpoints and the tracers.
//!
//! - Id 0 is air and cannot be redefined.
//! - Scenes register their materials by name when they are built (the
//!   terrain's `grass`, `rock`…, the simulation's `water`, `snow`,
//!   `sediment`); scripts' `materials.lua` adds more.
//! - A name keeps its id for the life of a world: re-registering it (a hot
//!   reload) may change its colour or properties, never its id. Only a
//!   start may [`remove`](MaterialRegistry::remove) a name, one that no
//!   file declares and no stored voxel holds
//!   (`engine::persistence::reclaim_materials`). New names
//!   take the highest free id, counting down from 251, so they do not collide
//!   with scene palettes that count up from 1.
//! - Checkpoints save the name of every id (see [`MaterialRegistry::names`]),
//!   so ids survive a restart whatever order materials are declared in.
//!
//! ```
//! use brickworld::world::{MaterialDef, MaterialKind, MaterialRegistry};
//! let mut reg = MaterialRegistry::new();
//! let lava = reg.register("lava", MaterialDef { color: [255, 90, 20], kind: MaterialKind::Liquid, density: 3.1 }).unwrap();
//! assert_eq!(reg.id("lava"), Some(lava));
//! // A reload keeps the id.
//! let again = reg.register("lava", MaterialDef { color: [250, 80, 10], kind: MaterialKind::Liquid, density: 3.1 }).unwrap();
//! assert_eq!(again, lava);
//! ```

use rustc_hash::FxHashMap;
use thiserror::Error;

use super::Palette;

/// How a material behaves (rules read it; the engine does not).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
#[repr(u8)]
pub enum MaterialKind {
    /// Stays put unless a rule moves it.
    Solid,
    /// Flows (water, lava).
    Liquid,
    /// Falls and piles (sand).
    Granular,
    /// Rises or spreads (steam).
    Gas,
}

impl std::str::FromStr for MaterialKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Ok(match s {
            "solid" => MaterialKind::Solid,
            "liquid" => MaterialKind::Liquid,
            "granular" => MaterialKind::Granular,
            "gas" => MaterialKind::Gas,
            other => {
                return Err(format!(
                    "kind '{other}' is not solid, liquid, granular or gas"
                ));
            }
        })
    }
}

/// A material's properties.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MaterialDef {
    /// Colour (sRGB).
    pub color: [u8; 3],
    /// Behaviour.
    pub kind: MaterialKind,
    /// Density relative to water.
    pub density: f32,
}

/// A material id (0 is air).
pub type MaterialId = u8;

/// Errors of the registry.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum MaterialError {
    /// A name that is not letters, digits and `_`, or `air`.
    #[error("material name '{0}' must be letters, digits and '_' (and not 'air')")]
    BadName(String),
    /// Every id a new name may take is taken.
    #[error(
        "no free material id for '{0}': ids 1 to 251 are all taken (a name no file declares keeps its id while the engine runs, since voxels may hold it; a restart frees the ids of names that nothing declares and no stored voxel holds)"
    )]
    Full(String),
    /// A property out of range.
    #[error("material '{name}': {msg}")]
    Bad {
        /// The material.
        name: String,
        /// What is wrong.
        msg: String,
    },
}

/// A name as an error shows it: escaped, at most 80 characters.
fn cut(name: &str) -> String {
    crate::text::shown(name, 80)
}

/// Named materials with stable ids.
#[derive(Clone, Debug)]
pub struct MaterialRegistry {
    defs: Vec<Option<(String, MaterialDef)>>,
    by_name: FxHashMap<String, MaterialId>,
    /// Names [`remove`](Self::remove)d: a stored registry may still list
    /// them (see [`disagreement`](Self::disagreement)).
    removed: rustc_hash::FxHashSet<String>,
}

impl Default for MaterialRegistry {
    fn default() -> Self {
        Self::new()
    }
}

impl MaterialRegistry {
    /// A registry with only air.
    pub fn new() -> Self {
        MaterialRegistry {
            defs: vec![None; 256],
            by_name: FxHashMap::default(),
            removed: Default::default(),
        }
    }

    /// Register `name` at a given id (scenes, whose voxels already carry
    /// ids). An id that holds another name is renamed; the old name is gone.
    pub fn register_at(
        &mut self,
        id: MaterialId,
        name: &str,
        def: MaterialDef,
    ) -> Result<MaterialId, MaterialError> {
        Self::check(name, &def)?;
        if id == 0 {
            return Err(MaterialError::BadName(cut(name)));
        }
        if let Some(Some((old, _))) = self.defs.get(id as usize) {
            let old = old.clone();
            self.by_name.remove(&old);
        }
        if let Some(prev) = self.by_name.insert(name.to_string(), id)
            && prev != id
        {
            self.defs[prev as usize] = None;
        }
        self.defs[id as usize] = Some((name.to_string(), def));
        self.removed.remove(name);
        Ok(id)
    }

    /// Register `name`: an existing name keeps its id (its properties are
    /// updated); a new one takes the highest free id.
    pub fn register(&mut self, name: &str, def: MaterialDef) -> Result<MaterialId, MaterialError> {
        Self::check(name, &def)?;
        if let Some(&id) = self.by_name.get(name) {
            self.defs[id as usize] = Some((name.to_string(), def));
            return Ok(id);
        }
        let id = (1..=251u8)
            .rev()
            .find(|&i| self.defs[i as usize].is_none())
            .ok_or_else(|| MaterialError::Full(cut(name)))?;
        self.register_at(id, name, def)
    }

    /// How many ids a new name could still take (of 1 to 251).
    pub fn free_ids(&self) -> usize {
        (1..=251usize).filter(|&i| self.defs[i].is_none()).count()
    }

    /// Forget `name`, freeing its id for a new name; its id, or None if it
    /// was not registered. Only for a name no voxel holds (see
    /// `engine::persistence::reclaim_materials`): a voxel holding the id
    /// would take the next name given it.
    pub fn remove(&mut self, name: &str) -> Option<MaterialId> {
        let id = self.by_name.remove(name)?;
        self.defs[id as usize] = None;
        self.removed.insert(name.to_string());
        Some(id)
    }

    /// Whether `name` may name a material: 1 to 64 ASCII letters, digits
    /// and `_`, and not `air`.
    pub fn valid_name(name: &str) -> bool {
        !name.is_empty()
            && name != "air"
            && name.len() <= 64
            && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
    }

    fn check(name: &str, def: &MaterialDef) -> Result<(), MaterialError> {
        if !Self::valid_name(name) {
            return Err(MaterialError::BadName(cut(name)));
        }
        if !(def.density.is_finite() && def.density >= 0.0) {
            return Err(MaterialError::Bad {
                name: name.into(),
                msg: format!("density {} must be a finite number >= 0", def.density),
            });
        }
        Ok(())
    }

    /// The id of `name` (`air` is 0).
    pub fn id(&self, name: &str) -> Option<MaterialId> {
        if name == "air" {
            return Some(0);
        }
        self.by_name.get(name).copied()
    }

    /// The material at `id`, if one is registered.
    pub fn get(&self, id: MaterialId) -> Option<(&str, &MaterialDef)> {
        self.defs[id as usize]
            .as_ref()
            .map(|(n, d)| (n.as_str(), d))
    }

    /// Every registered (id, name), by id.
    pub fn names(&self) -> Vec<(MaterialId, String)> {
        self.defs
            .iter()
            .enumerate()
            .filter_map(|(i, d)| d.as_ref().map(|(n, _)| (i as u8, n.clone())))
            .collect()
    }

    /// Every registered material as (id, name, kind, density), by id (what
    /// checkpoints save; colours live in the palette).
    pub fn entries(&self) -> Vec<(MaterialId, String, MaterialKind, f32)> {
        self.defs
            .iter()
            .enumerate()
            .filter_map(|(i, d)| {
                d.as_ref()
                    .map(|(n, d)| (i as u8, n.clone(), d.kind, d.density))
            })
            .collect()
    }

    /// Rebuild a registry from [`entries`](Self::entries), colours from `palette`.
    pub fn from_entries(
        entries: &[(MaterialId, String, MaterialKind, f32)],
        palette: &Palette,
    ) -> Self {
        let mut r = MaterialRegistry::new();
        for (id, name, kind, density) in entries {
            let _ = r.register_at(
                *id,
                name,
                MaterialDef {
                    color: palette.rgb(*id),
                    kind: *kind,
                    density: *density,
                },
            );
        }
        r
    }

    /// `stored` (the ids a store's voxels hold) with this registry's names
    /// added where they fit: a name `stored` lacks keeps its id here if that
    /// id is free there. A world that resumes loads `materials.lua` and its
    /// scripts against this, so that a name keeps its stored id and a new
    /// one takes a free id, as a hot reload would give it (regression: the
    /// scripts were loaded against a fresh registry, where a name declared
    /// before the others shifted their ids, and then the stored registry
    /// replaced it under them).
    pub fn under(&self, stored: &MaterialRegistry) -> MaterialRegistry {
        let mut r = stored.clone();
        for (i, d) in self.defs.iter().enumerate() {
            if let Some((name, def)) = d
                && r.id(name).is_none()
                && r.defs[i].is_none()
            {
                r.defs[i] = Some((name.clone(), *def));
                r.by_name.insert(name.clone(), i as MaterialId);
            }
        }
        r
    }

    /// The first of `stored`'s materials that this registry lacks or gives
    /// another id, as "name (id N)": None when every stored name keeps its
    /// id here. Names this registry [`remove`](Self::remove)d on purpose
    /// do not count.
    pub fn disagreement(&self, stored: &MaterialRegistry) -> Option<String> {
        stored
            .names()
            .into_iter()
            .filter(|(_, name)| !self.removed.contains(name))
            .find(|(id, name)| self.id(name) != Some(*id))
            .map(|(id, name)| format!("{name} (id {id})"))
    }

    /// Write every registered colour into `palette`.
    pub fn apply(&self, palette: &mut Palette) {
        for (i, d) in self.defs.iter().enumerate() {
            if let Some((_, def)) = d {
                palette.set(i as u8, def.color);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn def(c: u8) -> MaterialDef {
        MaterialDef {
            color: [c, c, c],
            kind: MaterialKind::Solid,
            density: 1.0,
        }
    }

    #[test]
    fn names_keep_their_ids_and_new_ones_count_down() {
        let mut r = MaterialRegistry::new();
        r.register_at(1, "grass", def(1)).unwrap();
        let a = r.register("lava", def(2)).unwrap();
        let b = r.register("steam", def(3)).unwrap();
        assert_eq!((a, b), (251, 250));
        assert_eq!(r.register("lava", def(9)).unwrap(), 251);
        assert_eq!(r.get(251).unwrap().1.color, [9, 9, 9]);
        assert_eq!(r.id("air"), Some(0));
        assert!(r.register("air", def(1)).is_err());
        assert!(r.register("no spaces", def(1)).is_err());
        let mut p = Palette::grey_ramp();
        r.apply(&mut p);
        assert_eq!(p.rgb(251), [9, 9, 9]);
    }

    #[test]
    fn a_registry_under_a_stored_one_keeps_the_stored_ids() {
        let mut stored = MaterialRegistry::new();
        stored.register_at(1, "grass", def(1)).unwrap();
        stored.register("basalt", def(2)).unwrap(); // 251
        stored.register("lava", def(3)).unwrap(); // 250
        // A fresh start gives acid, declared first, the id stored for basalt.
        let mut fresh = MaterialRegistry::new();
        fresh.register_at(1, "grass", def(9)).unwrap();
        fresh.register_at(2, "rock", def(9)).unwrap();
        fresh.register("acid", def(4)).unwrap();
        assert_eq!(fresh.id("acid"), Some(251));
        assert_eq!(
            fresh.disagreement(&stored).as_deref(),
            Some("lava (id 250)")
        );
        let mut r = fresh.under(&stored);
        assert_eq!(r.disagreement(&stored), None);
        assert_eq!(r.id("acid"), None, "its id is taken there");
        assert_eq!(r.id("rock"), Some(2), "a free id is kept");
        assert_eq!(r.get(1).unwrap().1.color, [1, 1, 1], "stored wins");
        // materials.lua then registers onto it: acid takes a free id.
        assert_eq!(r.register("acid", def(4)).unwrap(), 249);
        assert_eq!(r.register("lava", def(5)).unwrap(), 250);
        assert_eq!(r.disagreement(&stored), None);
    }

    #[test]
    fn the_registry_fills_up_with_a_clear_error() {
        let mut r = MaterialRegistry::new();
        for i in 0..251 {
            r.register(&format!("m{i}"), def(1)).unwrap();
        }
        assert!(matches!(
            r.register("one_more", def(1)),
            Err(MaterialError::Full(_))
        ));
        assert_eq!(r.free_ids(), 0);
        // A name removed frees its id for the next new name, and only it.
        let id = r.id("m7").unwrap();
        assert_eq!(r.remove("m7"), Some(id));
        assert_eq!((r.id("m7"), r.get(id), r.free_ids()), (None, None, 1));
        assert_eq!(r.remove("m7"), None);
        assert_eq!(r.register("one_more", def(2)).unwrap(), id);
        assert_eq!(r.free_ids(), 0);
        // A stored registry that still lists the removed name agrees;
        // one whose other names moved does not.
        let mut stored = MaterialRegistry::new();
        stored.register_at(id, "m7", def(1)).unwrap();
        stored
            .register_at(r.id("m8").unwrap(), "m8", def(1))
            .unwrap();
        assert_eq!(r.disagreement(&stored), None);
        stored.register_at(1, "m9", def(1)).unwrap();
        assert!(r.disagreement(&stored).unwrap().starts_with("m9 (id 1)"));
    }
}
