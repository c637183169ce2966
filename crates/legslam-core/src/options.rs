//! Named options of the engine's configurations, for configuration files and bindings. Each
//! configuration struct has one table (the [`options!`](crate::options) macro) that lists every
//! option once, by name, field and kind: reading, writing and listing options cannot drift
//! apart, and a value keeps its kind (a flag is a bool, a count an integer) from the file to the
//! field.

/// An option's value, in the kinds configuration files and Python know.
#[derive(Clone, Debug, PartialEq)]
pub enum Value {
    Bool(bool),
    Int(u64),
    Real(f64),
    Ints(Vec<usize>),
}

impl Value {
    /// What a value of this kind is, for messages ("a whole number >= 0").
    pub fn kind(&self) -> &'static str {
        match self {
            Value::Bool(_) => "true or false",
            Value::Int(_) => "a whole number >= 0",
            Value::Real(_) => "a number",
            Value::Ints(_) => "a list of whole numbers >= 0",
        }
    }
}

/// A configuration with named options.
pub trait Options: Default {
    /// (name, value) of every option, in the table's order.
    fn entries(&self) -> Vec<(&'static str, Value)>;
    /// Sets one option; an unknown name or a value of the wrong kind is an error naming both.
    fn set(&mut self, name: &str, value: Value) -> Result<(), String>;
}

/// Refuses a non-finite (NaN or infinite) real option, by name: the first check of every
/// configuration's `validate`.
pub fn check_finite(section: &str, options: &impl Options) -> Result<(), String> {
    for (name, v) in options.entries() {
        if let Value::Real(x) = v {
            if !x.is_finite() {
                return Err(format!("{section} option {name} must be finite, got {x}"));
            }
        }
    }
    Ok(())
}

/// The conversion of a [`Value`] into a field's type.
pub trait OptionField: Sized {
    fn to_value(&self) -> Value;
    fn from_value(v: Value) -> Result<Self, Value>;
}

impl OptionField for bool {
    fn to_value(&self) -> Value {
        Value::Bool(*self)
    }
    fn from_value(v: Value) -> Result<Self, Value> {
        match v {
            Value::Bool(b) => Ok(b),
            other => Err(other),
        }
    }
}

impl OptionField for usize {
    fn to_value(&self) -> Value {
        Value::Int(*self as u64)
    }
    fn from_value(v: Value) -> Result<Self, Value> {
        match v {
            Value::Int(i) => usize::try_from(i).map_err(|_| Value::Int(i)),
            other => Err(other),
        }
    }
}

impl OptionField for u64 {
    fn to_value(&self) -> Value {
        Value::Int(*self)
    }
    fn from_value(v: Value) -> Result<Self, Value> {
        match v {
            Value::Int(i) => Ok(i),
            other => Err(other),
        }
    }
}

/// Real options take whole numbers too (`depth_max = 10` in a file means 10.0).
impl OptionField for f64 {
    fn to_value(&self) -> Value {
        Value::Real(*self)
    }
    fn from_value(v: Value) -> Result<Self, Value> {
        match v {
            Value::Real(x) => Ok(x),
            Value::Int(i) => Ok(i as f64),
            other => Err(other),
        }
    }
}

#[cfg(not(feature = "f64"))]
impl OptionField for f32 {
    /// The shortest decimal that reads back as the same f32 (0.2, not 0.20000000298023224).
    fn to_value(&self) -> Value {
        Value::Real(self.to_string().parse().unwrap_or(f64::from(*self)))
    }
    fn from_value(v: Value) -> Result<Self, Value> {
        f64::from_value(v).map(|x| x as f32)
    }
}

/// The rasterizer's implementation, as a flag: `true` for the CPU's best (`Auto`), `false` for
/// the portable path. Code may pin one implementation (the benchmarks compare them); its flag
/// then reads `true`, since it is a vector path.
impl OptionField for crate::raster::Simd {
    fn to_value(&self) -> Value {
        Value::Bool(*self != crate::raster::Simd::Portable)
    }
    fn from_value(v: Value) -> Result<Self, Value> {
        use crate::raster::Simd;
        bool::from_value(v).map(|b| if b { Simd::Auto } else { Simd::Portable })
    }
}

impl OptionField for Vec<usize> {
    fn to_value(&self) -> Value {
        Value::Ints(self.clone())
    }
    fn from_value(v: Value) -> Result<Self, Value> {
        match v {
            Value::Ints(v) => Ok(v),
            other => Err(other),
        }
    }
}

/// Implements [`Options`] for a configuration struct from its table:
/// `options!(MapperConfig, "mapper", { "levels" => levels, "loss_depth" => loss.depth, ... })`.
#[macro_export]
macro_rules! options {
    ($config:ty, $section:literal, { $($name:literal => $($field:ident).+),* $(,)? }) => {
        impl $crate::options::Options for $config {
            fn entries(&self) -> Vec<(&'static str, $crate::options::Value)> {
                use $crate::options::OptionField;
                vec![$(($name, self.$($field).+.to_value())),*]
            }

            fn set(&mut self, name: &str, value: $crate::options::Value) -> Result<(), String> {
                use $crate::options::OptionField;
                match name {
                    $($name => {
                        self.$($field).+ = OptionField::from_value(value).map_err(|v| {
                            $crate::options::wrong_kind($section, name, &self.$($field).+.to_value(), &v)
                        })?;
                    })*
                    _ => {
                        return Err(format!(
                            "unknown {} option {name:?}; known: {}",
                            $section,
                            [$($name),*].join(", ")
                        ))
                    }
                }
                Ok(())
            }
        }
    };
}

/// The error for option `name` given `got` where its kind is that of `want`.
pub fn wrong_kind(section: &str, name: &str, want: &Value, got: &Value) -> String {
    let shown = match got {
        Value::Bool(b) => b.to_string(),
        Value::Int(i) => i.to_string(),
        Value::Real(x) => x.to_string(),
        Value::Ints(v) => format!("{v:?}"),
    };
    format!(
        "{section} option {name} must be {}, got {shown}",
        want.kind()
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Default, Debug, PartialEq)]
    struct Inner {
        rate: f64,
    }

    #[derive(Default, Debug, PartialEq)]
    struct Demo {
        flag: bool,
        count: usize,
        steps: Vec<usize>,
        inner: Inner,
    }

    crate::options!(Demo, "demo", {
        "flag" => flag,
        "count" => count,
        "steps" => steps,
        "rate" => inner.rate,
    });

    #[test]
    fn every_option_reads_and_writes_its_own_field() {
        let mut d = Demo::default();
        d.set("flag", Value::Bool(true)).unwrap();
        d.set("count", Value::Int(3)).unwrap();
        d.set("steps", Value::Ints(vec![4, 2])).unwrap();
        d.set("rate", Value::Int(2)).unwrap(); // a whole number is a number
        let want = Demo {
            flag: true,
            count: 3,
            steps: vec![4, 2],
            inner: Inner { rate: 2.0 },
        };
        assert_eq!(d, want);
        let names: Vec<_> = d.entries().into_iter().map(|(n, _)| n).collect();
        assert_eq!(names, ["flag", "count", "steps", "rate"]);
        assert_eq!(d.entries()[3].1, Value::Real(2.0));
    }

    #[test]
    fn a_value_of_another_kind_or_an_unknown_name_is_refused_by_name() {
        let mut d = Demo::default();
        let e = d.set("flag", Value::Int(1)).unwrap_err();
        assert!(e.contains("demo option flag must be true or false"), "{e}");
        let e = d.set("count", Value::Real(2.5)).unwrap_err();
        assert!(e.contains("count must be a whole number"), "{e}");
        let e = d.set("nope", Value::Int(1)).unwrap_err();
        assert!(
            e.contains("unknown demo option \"nope\"") && e.contains("rate"),
            "{e}"
        );
        assert_eq!(d, Demo::default(), "a refused value changes nothing");
        d.set("rate", Value::Real(f64::NAN)).unwrap();
        assert!(check_finite("demo", &d)
            .unwrap_err()
            .contains("rate must be finite"));
    }

    #[test]
    fn the_rasterizer_path_is_a_flag() {
        use crate::map::MapperConfig;
        use crate::raster::Simd;
        let mut c = MapperConfig::default();
        let flag = |c: &MapperConfig| c.entries().into_iter().find(|(n, _)| *n == "simd");
        assert_eq!(flag(&c).unwrap().1, Value::Bool(true));
        c.set("simd", Value::Bool(false)).unwrap();
        assert_eq!(
            (c.simd, flag(&c).unwrap().1),
            (Simd::Portable, Value::Bool(false))
        );
        c.set("simd", Value::Bool(true)).unwrap();
        assert_eq!(c.simd, Simd::Auto);
        c.simd = Simd::Avx2;
        assert_eq!(
            flag(&c).unwrap().1,
            Value::Bool(true),
            "a pinned path is a vector path"
        );
        let e = c.set("simd", Value::Int(1)).unwrap_err();
        assert!(e.contains("simd must be true or false"), "{e}");
    }
}
