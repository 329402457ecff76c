//! Command-line parsing of the library's option types (feature `clap`): the engine's
//! [`Choice`] enums (schedules, splits, backgrounds) parse by their own names through
//! [`choice`], so that the program keeps no mirror of them and the engine needs no clap.

#[cfg(feature = "clap")]
use ngp::choice::Choice;

/// clap's parser of a [`Choice`]: its names, each with its help line in `--help`.
#[cfg(feature = "clap")]
#[derive(Clone, Copy, Debug)]
pub struct ChoiceParser<T>(std::marker::PhantomData<T>);

/// `#[arg(value_parser = choice::<Schedule>())]`.
#[cfg(feature = "clap")]
pub fn choice<T: Choice>() -> ChoiceParser<T> {
    ChoiceParser(std::marker::PhantomData)
}

#[cfg(feature = "clap")]
impl<T: Choice> clap::builder::TypedValueParser for ChoiceParser<T> {
    type Value = T;

    fn parse_ref(
        &self,
        cmd: &clap::Command,
        arg: Option<&clap::Arg>,
        value: &std::ffi::OsStr,
    ) -> Result<T, clap::Error> {
        use clap::error::{ContextKind, ContextValue, ErrorKind};
        let text = value.to_string_lossy();
        T::from_name(&text).map_err(|_| {
            let mut e = clap::Error::new(ErrorKind::InvalidValue).with_cmd(cmd);
            if let Some(a) = arg {
                e.insert(ContextKind::InvalidArg, ContextValue::String(a.to_string()));
            }
            e.insert(ContextKind::InvalidValue, ContextValue::String(text.into()));
            e.insert(
                ContextKind::ValidValue,
                ContextValue::Strings(T::ALL.iter().map(|c| c.name().to_owned()).collect()),
            );
            e
        })
    }

    fn possible_values(
        &self,
    ) -> Option<Box<dyn Iterator<Item = clap::builder::PossibleValue> + '_>> {
        Some(Box::new(T::ALL.iter().map(|c| {
            clap::builder::PossibleValue::new(c.name()).help(c.help())
        })))
    }
}

#[cfg(all(test, feature = "clap"))]
mod tests {
    use super::*;
    use clap::Parser;
    use ngp::train::Schedule;

    #[derive(Parser, Debug)]
    struct Args {
        #[arg(long, value_parser = choice::<Schedule>(), default_value_t = Schedule::Mixed)]
        schedule: Schedule,
    }

    #[test]
    fn choices_parse_by_name_and_refuse_the_rest() {
        let a = Args::try_parse_from(["t", "--schedule", "random-scene"]).unwrap();
        assert_eq!(a.schedule, Schedule::RandomScene);
        assert_eq!(
            Args::try_parse_from(["t"]).unwrap().schedule,
            Schedule::Mixed
        );
        let e = Args::try_parse_from(["t", "--schedule", "fast"])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("'fast'") && e.contains("mixed") && e.contains("random-scene"),
            "{e}"
        );
    }
}
