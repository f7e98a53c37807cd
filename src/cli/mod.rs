//! Subcommands other than `serve`.

pub mod bench;
pub mod bundles;
pub mod domains;
pub mod evaluate;
pub mod inspect;
#[cfg(feature = "render")]
pub mod render;
#[cfg(feature = "train")]
pub mod train;

/// Two finite numbers "A,B" from a command-line value (`--value-scale`, prac-sim's
/// `--normalize`); `what` names the flag's form in the error.
pub fn parse_number_pair(text: &str, what: &str) -> anyhow::Result<(f64, f64)> {
    let numbers: Vec<f64> = text
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| anyhow::anyhow!("expected {what} (two numbers), got '{text}'"))?;
    match numbers[..] {
        [a, b] if a.is_finite() && b.is_finite() => Ok((a, b)),
        _ => anyhow::bail!("expected {what} (two finite numbers), got '{text}'"),
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn number_pairs_take_exactly_two_finite_numbers() {
        assert_eq!(super::parse_number_pair("1,2", "A,B").unwrap(), (1.0, 2.0));
        assert_eq!(
            super::parse_number_pair(" -3 , 4.5", "A,B").unwrap(),
            (-3.0, 4.5)
        );
        for bad in ["1", "1,2,3", "a,b", "nan,1", "1,inf", ""] {
            let e = super::parse_number_pair(bad, "A,B").unwrap_err();
            assert!(e.to_string().contains("A,B"), "{bad}: {e}");
        }
    }
}
