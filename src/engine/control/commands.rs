//! Turning a `POST` into a [`Command`]: each route's body parsed and
//! checked against what `/status` shows (scripts and their parameter
//! ranges), or a 4xx with the reason. The engine checks again when it
//! applies a command, in case a hot reload changed the ranges meanwhile.

use super::exchange::VerdictSlot;
use super::routes::{percent_decoded, shown};
use super::{Command, Status};

/// Turn a `POST` into a command, validated against what `/status` shows
/// (scripts and their parameter ranges). The engine checks again when it
/// applies the command, in case a hot reload changed the ranges meanwhile.
pub fn parse_command(path: &str, body: &str, status: &Status) -> Result<Command, (u16, String)> {
    let bad = |m: String| (400u16, m);
    match path {
        "/pause" => Ok(Command::Pause),
        "/resume" => Ok(Command::Resume),
        "/checkpoint" | "/commit" => Ok(Command::Checkpoint {
            verdict: VerdictSlot::default(),
        }),
        "/step" => {
            let t = body.trim();
            let n = if t.is_empty() {
                1
            } else {
                match t.parse::<u64>() {
                    Ok(n) => n,
                    // All digits, past u64: out of range, not malformed.
                    Err(_) if t.bytes().all(|b| b.is_ascii_digit()) => u64::MAX,
                    Err(_) => {
                        return Err(bad(format!(
                            "step count '{}' is not a whole number",
                            shown(t)
                        )));
                    }
                }
            };
            if !(1..=100_000).contains(&n) {
                // The count as sent, not the 64-bit limit it was read as.
                return Err(bad(format!(
                    "step count {} is outside 1..=100000",
                    shown(t)
                )));
            }
            Ok(Command::Step(n))
        }
        "/camera/path" => {
            // An empty body: an administrative return, which always wins; a
            // viewer names itself and is held to the camera lease like its
            // moves (found by the viewer probe: any page took the camera
            // from the viewer holding it).
            #[derive(serde::Deserialize)]
            #[serde(deny_unknown_fields)]
            struct Back {
                viewer: Option<String>,
            }
            let viewer = if body.trim().is_empty() {
                None
            } else {
                let b: Back = serde_json::from_str(body)
                    .map_err(|e| bad(format!("camera/path JSON: {e}")))?;
                b.viewer
            };
            check_viewer(viewer.as_deref())?;
            Ok(Command::CameraPath { viewer })
        }
        "/camera" => {
            #[derive(serde::Deserialize)]
            #[serde(deny_unknown_fields)]
            struct Cam {
                eye: [f64; 3],
                target: [f64; 3],
                fov: Option<f64>,
                viewer: Option<String>,
            }
            let c: Cam =
                serde_json::from_str(body).map_err(|e| bad(format!("camera JSON: {e}")))?;
            let fov = c.fov.unwrap_or(50.0);
            for (name, p) in [("eye", c.eye), ("target", c.target)] {
                if p.iter().any(|v| !v.is_finite() || v.abs() > 1e9) {
                    return Err(bad(format!(
                        "camera {name}: every coordinate must be finite and within ±1e9 voxels"
                    )));
                }
            }
            if !(crate::trace::MIN_FOV..=crate::trace::MAX_FOV).contains(&fov) {
                return Err(bad(format!(
                    "fov {} is outside 0.01..=179 degrees",
                    crate::sim::fmt_num(fov)
                )));
            }
            crate::trace::Camera::new(c.eye.into(), c.target.into(), fov, 8, 8)
                .map_err(|e| bad(e.to_string()))?;
            check_viewer(c.viewer.as_deref())?;
            Ok(Command::Camera {
                eye: c.eye,
                target: c.target,
                fov,
                viewer: c.viewer,
            })
        }
        p if p.starts_with("/scripts/")
            && p.ends_with("/params")
            && p.len() > "/scripts//params".len() - 1 =>
        {
            let raw = &p["/scripts/".len()..p.len() - "/params".len()];
            if raw.is_empty() || raw.contains('/') {
                return Err((404, format!("no route POST {}", shown(p))));
            }
            let Some(script) = percent_decoded(raw) else {
                return Err(bad(format!(
                    "the script name '{}' is not valid percent-encoded UTF-8",
                    shown(raw)
                )));
            };
            let script = script.as_str();
            let Some(s) = status.scripts.iter().find(|s| s.name == script) else {
                let loaded: Vec<&str> = status.scripts.iter().map(|s| s.name.as_str()).collect();
                return Err(bad(format!(
                    "no script named '{}' (loaded: {})",
                    shown(&script.escape_debug().to_string()),
                    loaded.join(", ")
                )));
            };
            let map = serde_json::from_str::<UniqueNumbers>(body)
                .map_err(|e| bad(format!("params JSON (an object of numbers): {e}")))?
                .0;
            if map.is_empty() {
                return Err(bad("params JSON names no parameter".into()));
            }
            for (k, v) in &map {
                let Some(p) = s.params.iter().find(|p| &p.name == k) else {
                    let known: Vec<&str> = s.params.iter().map(|p| p.name.as_str()).collect();
                    return Err(bad(format!(
                        "script '{script}' has no parameter '{}' ({})",
                        shown(k),
                        crate::sim::runtime::spec::known_params(&known)
                    )));
                };
                if !v.is_finite() || !(p.min..=p.max).contains(v) {
                    return Err(bad(format!(
                        "parameter '{k}' = {} is outside [{}, {}]",
                        crate::sim::fmt_num(*v),
                        crate::sim::fmt_num(p.min),
                        crate::sim::fmt_num(p.max)
                    )));
                }
            }
            Ok(Command::Params {
                script: script.to_string(),
                values: map.into_iter().collect(),
                verdict: VerdictSlot::default(),
            })
        }
        other => Err((404, format!("no route POST {}", shown(other)))),
    }
}

/// A JSON object of numbers whose keys are all different (regression:
/// `{"rain":0.1,"rain":0.2}` was applied, last one winning, while
/// `/camera` refused duplicate fields).
struct UniqueNumbers(std::collections::BTreeMap<String, f64>);

impl<'de> serde::Deserialize<'de> for UniqueNumbers {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visit;
        impl<'de> serde::de::Visitor<'de> for Visit {
            type Value = UniqueNumbers;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("an object of numbers")
            }
            fn visit_map<A: serde::de::MapAccess<'de>>(
                self,
                mut m: A,
            ) -> Result<UniqueNumbers, A::Error> {
                let mut out = std::collections::BTreeMap::new();
                while let Some((k, v)) = m.next_entry::<String, f64>()? {
                    if out.contains_key(&k) {
                        return Err(serde::de::Error::custom(format!(
                            "duplicate parameter '{}'",
                            shown(&k)
                        )));
                    }
                    out.insert(k, v);
                }
                Ok(UniqueNumbers(out))
            }
        }
        d.deserialize_map(Visit)
    }
}

/// A viewer id, if given, is 1 to 64 letters, digits, '-' or '_'.
fn check_viewer(viewer: Option<&str>) -> Result<(), (u16, String)> {
    match viewer {
        Some(v)
            if v.is_empty()
                || v.len() > 64
                || !v
                    .chars()
                    .all(|ch| ch.is_ascii_alphanumeric() || ch == '-' || ch == '_') =>
        {
            Err((
                400,
                format!(
                    "viewer id '{}' must be 1 to 64 letters, digits, '-' or '_'",
                    shown(v)
                ),
            ))
        }
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Regression (review): a parameter sent through the API was parsed
    /// one unit in the last place off the same text in the world config
    /// (serde_json's fast float parse), so `ctl param water rain
    /// 0.012345678901234567` stored another value than the config's, and
    /// the start warned of the difference for ever. JSON numbers now parse
    /// exactly, as Rust's `str::parse` does.
    #[test]
    fn api_parameters_parse_exactly_as_the_config_does() {
        for text in [
            "0.012345678901234567",
            "0.1",
            "2.2250738585072014e-308",
            "1e-320",
            "123456789.12345678",
            "0.30000000000000004",
        ] {
            let map = serde_json::from_str::<UniqueNumbers>(&format!("{{\"p\": {text}}}"))
                .unwrap()
                .0;
            let want: f64 = text.parse().unwrap();
            assert_eq!(map["p"].to_bits(), want.to_bits(), "{text}");
        }
    }

    /// Regression (hostile probe): a step count past 64 bits was said not
    /// to be a whole number, and then quoted as 18446744073709551615 (the
    /// limit it was read as), a number the client never sent.
    #[test]
    fn a_step_count_past_64_bits_is_out_of_range_not_malformed() {
        let status = Status::default();
        for (body, says) in [
            (
                "99999999999999999999999",
                "99999999999999999999999 is outside 1..=100000",
            ),
            ("100001", "is outside 1..=100000"),
            ("0", "is outside 1..=100000"),
            ("-1", "'-1' is not a whole number"),
            ("1e3", "'1e3' is not a whole number"),
        ] {
            let (code, msg) = parse_command("/step", body, &status).unwrap_err();
            assert_eq!(code, 400, "{body}");
            assert!(msg.contains(says), "{body}: {msg}");
        }
        assert!(matches!(
            parse_command("/step", " 7 ", &status),
            Ok(Command::Step(7))
        ));
    }
}
