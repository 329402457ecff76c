//! Options chosen by name from a fixed list (a schedule, a split, a background). The engine
//! names its choices and parses them; a command line (clap, in the stego layer's
//! `options::choice`) or a config file builds on that, so the engine needs no parser
//! library and the program keeps no mirror of its enums.

/// An enum whose values have names (and a line of help each).
pub trait Choice: Copy + Sized + Send + Sync + 'static {
    /// Every value, in the order a help text lists them.
    const ALL: &'static [Self];

    /// The value's name, as a command line takes it.
    fn name(self) -> &'static str;

    /// One line on what the value does.
    fn help(self) -> &'static str;

    /// The value named `s`, or an error listing the names.
    fn from_name(s: &str) -> Result<Self, String> {
        Self::ALL
            .iter()
            .copied()
            .find(|c| c.name() == s)
            .ok_or_else(|| {
                let names: Vec<&str> = Self::ALL.iter().map(|c| c.name()).collect();
                format!("`{s}`: one of {}", names.join(", "))
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::Split;
    use crate::render::image::Background;
    use crate::train::Schedule;

    fn round_trips<T: Choice + PartialEq + std::fmt::Debug>() {
        for &c in T::ALL {
            assert_eq!(T::from_name(c.name()), Ok(c));
            assert!(!c.help().is_empty(), "{c:?} has no help");
        }
    }

    #[test]
    fn every_choice_parses_its_own_name() {
        round_trips::<Split>();
        round_trips::<Background>();
        round_trips::<Schedule>();
        let e = Schedule::from_name("fast").unwrap_err();
        assert!(
            e.contains("`fast`") && e.contains("mixed, random-scene"),
            "{e}"
        );
    }
}
