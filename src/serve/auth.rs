//! Optional bearer-token auth: `--auth-tokens FILE` holds one token per line (blank lines and
//! `#` comments ignored). Every prac.v1 call must carry `authorization: Bearer TOKEN`; health
//! and reflection stay open for probes. A caller is known by a digest of its token (the token
//! itself is never stored or logged), and a session belongs to the caller that opened it.

use std::collections::HashSet;
use std::path::Path;

use anyhow::Context;
use sha2::{Digest, Sha256};
use tonic::Status;

pub(super) struct Tokens {
    digests: HashSet<[u8; 32]>,
}

fn digest(token: &str) -> [u8; 32] {
    Sha256::digest(token.as_bytes()).into()
}

impl Tokens {
    pub(super) fn load(path: &Path) -> anyhow::Result<Tokens> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read auth tokens {}", path.display()))?;
        Tokens::parse(&text).with_context(|| format!("auth tokens {}", path.display()))
    }

    pub(super) fn parse(text: &str) -> anyhow::Result<Tokens> {
        let mut digests = HashSet::new();
        for (i, line) in text.lines().enumerate() {
            let token = line.trim();
            if token.is_empty() || token.starts_with('#') {
                continue;
            }
            anyhow::ensure!(
                token.len() >= 16 && !token.contains(char::is_whitespace),
                "line {}: a token must be at least 16 characters without spaces",
                i + 1
            );
            digests.insert(digest(token));
        }
        anyhow::ensure!(!digests.is_empty(), "no tokens");
        Ok(Tokens { digests })
    }

    /// The caller's identity from a request's HTTP/2 headers: a hex digest prefix of its token.
    pub(super) fn caller(&self, headers: &http::HeaderMap) -> Result<String, Status> {
        let value = headers.get("authorization").ok_or_else(|| {
            Status::unauthenticated("missing 'authorization: Bearer TOKEN' metadata")
        })?;
        let token = value
            .to_str()
            .ok()
            .and_then(|v| v.strip_prefix("Bearer "))
            .ok_or_else(|| Status::unauthenticated("authorization must be 'Bearer TOKEN'"))?;
        let d = digest(token.trim());
        if self.digests.contains(&d) {
            Ok(hex::encode(&d[..8]))
        } else {
            Err(Status::unauthenticated("invalid bearer token"))
        }
    }
}

/// Who made a prac.v1 call: with tokens on, the intake attaches it to the request from its
/// headers, once, and the handlers read it.
#[derive(Clone, Debug)]
pub(super) struct Caller(pub(super) Option<String>);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_identify_callers() {
        let tokens =
            Tokens::parse("# ops\nalpha-0123456789abcdef\n\nbeta-0123456789abcdef\n").unwrap();
        let mut md = http::HeaderMap::new();
        assert_eq!(
            tokens.caller(&md).unwrap_err().code(),
            tonic::Code::Unauthenticated
        );
        md.insert(
            "authorization",
            "Bearer alpha-0123456789abcdef".parse().unwrap(),
        );
        let alpha = tokens.caller(&md).unwrap();
        md.insert(
            "authorization",
            "Bearer beta-0123456789abcdef".parse().unwrap(),
        );
        assert_ne!(tokens.caller(&md).unwrap(), alpha);
        md.insert(
            "authorization",
            "Bearer gamma-0123456789abcdef".parse().unwrap(),
        );
        assert_eq!(
            tokens.caller(&md).unwrap_err().code(),
            tonic::Code::Unauthenticated
        );
        md.insert(
            "authorization",
            "Basic alpha-0123456789abcdef".parse().unwrap(),
        );
        assert_eq!(
            tokens.caller(&md).unwrap_err().code(),
            tonic::Code::Unauthenticated
        );
        assert!(Tokens::parse("# nothing\n").is_err());
        assert!(Tokens::parse("short\n").is_err());
    }
}
