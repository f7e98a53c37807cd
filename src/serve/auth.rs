//! Optional bearer-token auth: `--auth-tokens FILE` holds one token per line (blank lines and
//! `#` comments ignored). Every prac.v1 call must carry `authorization: Bearer TOKEN`; health
//! and reflection stay open for probes. A caller is known by a digest of its token (the token
//! itself is never stored or logged), and a session belongs to the caller that opened it. The
//! file is re-read while serving (`credentials`): a removed token is refused from its next call.

use std::collections::HashSet;
use std::sync::RwLock;

use sha2::{Digest, Sha256};
use tonic::Status;

pub(super) struct Tokens {
    digests: RwLock<HashSet<[u8; 32]>>,
}

fn digest(token: &str) -> [u8; 32] {
    Sha256::digest(token.as_bytes()).into()
}

impl Tokens {
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
        Ok(Tokens {
            digests: RwLock::new(digests),
        })
    }

    /// Serves `newer`'s tokens from the next call on.
    pub(super) fn replace_with(&self, newer: Tokens) {
        let digests = newer
            .digests
            .into_inner()
            .unwrap_or_else(|p| p.into_inner());
        *self.digests.write().unwrap_or_else(|p| p.into_inner()) = digests;
    }

    pub(super) fn len(&self) -> usize {
        self.digests.read().unwrap_or_else(|p| p.into_inner()).len()
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
        let known = self
            .digests
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .contains(&d);
        if known {
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
        let gamma = Tokens::parse("gamma-0123456789abcdef\n").unwrap();
        tokens.replace_with(gamma);
        assert_eq!(tokens.len(), 1);
        md.insert(
            "authorization",
            "Bearer gamma-0123456789abcdef".parse().unwrap(),
        );
        assert!(tokens.caller(&md).is_ok());
        md.insert(
            "authorization",
            "Bearer alpha-0123456789abcdef".parse().unwrap(),
        );
        assert!(tokens.caller(&md).is_err());
        assert!(Tokens::parse("# nothing\n").is_err());
        assert!(Tokens::parse("short\n").is_err());
    }
}
