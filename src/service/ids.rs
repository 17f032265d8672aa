//! Scan and job identifiers: 128 random bits as 32 lowercase hex digits, so ids cannot be
//! guessed or enumerated, and anything else in an id position is refused before it reaches
//! the file system (an id is also a directory name in the store).

use std::fmt;

/// Length of an id in hex digits.
const ID_HEX_LEN: usize = 32;

macro_rules! random_id {
    ($name:ident, $what:literal) => {
        #[doc = concat!("Identifier of a stored ", $what, " (32 lowercase hex digits).")]
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
        pub struct $name(u128);

        impl $name {
            #[doc = concat!("A new random ", $what, " id.")]
            pub fn random() -> Self {
                $name(uuid::Uuid::new_v4().as_u128())
            }

            #[doc = concat!("Parses a ", $what, " id; `None` unless it is exactly 32 lowercase hex digits.")]
            pub fn parse(text: &str) -> Option<Self> {
                parse_hex_id(text).map($name)
            }
        }

        impl fmt::Display for $name {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                write!(f, "{:032x}", self.0)
            }
        }

        impl serde::Serialize for $name {
            fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
                s.collect_str(self)
            }
        }

        impl<'de> serde::Deserialize<'de> for $name {
            fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
                let text = String::deserialize(d)?;
                $name::parse(&text).ok_or_else(|| {
                    serde::de::Error::custom(format!("{text:?} is not a {} id", $what))
                })
            }
        }
    };
}

random_id!(ScanId, "scan");
random_id!(JobId, "job");

fn parse_hex_id(text: &str) -> Option<u128> {
    if text.len() != ID_HEX_LEN
        || !text
            .bytes()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
    {
        return None;
    }
    u128::from_str_radix(text, 16).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_round_trip_and_refuse_anything_else() {
        let id = JobId::random();
        let text = id.to_string();
        assert_eq!(text.len(), 32);
        assert_eq!(JobId::parse(&text), Some(id));
        let json = serde_json::to_string(&id).unwrap();
        assert_eq!(serde_json::from_str::<JobId>(&json).unwrap(), id);
        assert_ne!(JobId::random(), JobId::random());
        for bad in [
            "",
            "..",
            "../../etc/passwd",
            &text.to_uppercase(),
            &text[1..],
            &format!("{text}0"),
            "+0000000000000000000000000000000",
        ] {
            assert_eq!(JobId::parse(bad), None, "{bad}");
        }
    }
}
