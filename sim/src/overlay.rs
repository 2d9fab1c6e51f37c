//! Overrides laid onto their base: below every configuration that takes
//! an override file (`PegConfig::with_overrides`, the learner's settings).

/// Lays `over` onto `base`: tables merge key by key, anything else
/// replaces. The one rule of every lcrl override: a peg file over its
/// preset, a training file over the environment's settings.
pub fn overlay(base: &mut toml::Table, over: &toml::Table) {
    for (key, value) in over {
        match (base.get_mut(key), value) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) => overlay(b, o),
            _ => {
                base.insert(key.clone(), value.clone());
            }
        }
    }
}
