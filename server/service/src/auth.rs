//! Who may do what: operators manage sessions; a session's tokens control or watch it.
//!
//! - An *operator* creates, lists and closes sessions and reads recordings. An operator
//!   is a caller that presents one of the configured operator tokens, or (with TLS) a
//!   client certificate issued by the operators' CA; in development mode, also any
//!   caller on loopback. An operator may close any session and watch any session.
//! - A session's *control* token moves its tools, runs scripts and closes it; its
//!   *observe* token watches it.
//!
//! Tokens are random, compared in constant time and never logged.

use std::net::SocketAddr;

use crate::error::ApiError;

/// The gRPC metadata key (and HTTP header) that carries a token.
pub const TOKEN_KEY: &str = "cutsim-token";
/// The gRPC metadata key that names the session of a haptics stream.
pub const SESSION_KEY: &str = "cutsim-session";
/// Configured tokens shorter than this are refused at start (guessable).
pub const MIN_TOKEN_CHARS: usize = 16;

/// What a session token lets its holder do.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Role {
    Observe,
    Control,
}

/// A 128-bit random token, shown as 32 hex digits.
#[derive(Clone, PartialEq, Eq)]
pub struct Token(String);

impl std::fmt::Debug for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Token(…)")
    }
}

impl Token {
    pub fn generate() -> Self {
        let mut bytes = [0u8; 16];
        getrandom::fill(&mut bytes).expect("the operating system provides random bytes");
        Self(bytes.iter().map(|b| format!("{b:02x}")).collect())
    }

    /// A token given in the configuration.
    pub fn from_string(token: String) -> Self {
        Self(token)
    }

    pub fn as_str(&self) -> &str {
        &self.0
    }

    /// Constant-time comparison (no early exit on the first differing byte).
    pub fn matches(&self, given: &str) -> bool {
        let (a, b) = (self.0.as_bytes(), given.as_bytes());
        if a.len() != b.len() {
            return false;
        }
        a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
    }
}

/// The role a presented token grants for a session with these tokens.
pub fn authorize(given: Option<&str>, control: &Token, observe: &Token, needed: Role) -> Result<Role, ApiError> {
    let Some(given) = given.filter(|g| !g.is_empty()) else {
        return Err(ApiError::Unauthenticated(format!("a session token is required (metadata or header `{TOKEN_KEY}`, or ?token= for WebSockets)")));
    };
    let role = if control.matches(given) {
        Role::Control
    } else if observe.matches(given) {
        Role::Observe
    } else {
        return Err(ApiError::Unauthenticated("the token is not valid for this session".into()));
    };
    if role < needed {
        return Err(ApiError::PermissionDenied("an observe token cannot control the session; use its control token".into()));
    }
    Ok(role)
}

/// What a request shows of its caller.
#[derive(Debug, Clone, Copy, Default)]
pub struct Caller<'a> {
    /// The token in metadata or header `cutsim-token`.
    pub token: Option<&'a str>,
    /// The connection's peer address.
    pub peer: Option<SocketAddr>,
    /// The caller presented a client certificate that the operators' CA signed (the TLS
    /// handshake verified it).
    pub operator_certificate: bool,
}

/// How an operator proved it is one (named in logs; never the token itself).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Operator {
    Token(String),
    Certificate,
    Loopback,
}

impl std::fmt::Display for Operator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Operator::Token(name) => write!(f, "operator {name:?}"),
            Operator::Certificate => f.write_str("an operator with a client certificate"),
            Operator::Loopback => f.write_str("a loopback caller (development mode)"),
        }
    }
}

/// The server's operators.
#[derive(Debug)]
pub struct Operators {
    tokens: Vec<(String, Token)>,
    /// Development mode: every caller on loopback is an operator.
    open_on_loopback: bool,
}

impl Operators {
    /// `tokens`: (name, token); each token at least [`MIN_TOKEN_CHARS`] characters.
    pub fn new(tokens: Vec<(String, String)>, open_on_loopback: bool) -> Result<Self, String> {
        for (name, token) in &tokens {
            if token.chars().count() < MIN_TOKEN_CHARS {
                return Err(format!("operator token {name:?} has {} characters; at least {MIN_TOKEN_CHARS} are needed (e.g. 32 hex digits)", token.chars().count()));
            }
        }
        Ok(Self { tokens: tokens.into_iter().map(|(n, t)| (n, Token::from_string(t))).collect(), open_on_loopback })
    }

    /// The operator a caller is, or why it is not one. Every token is compared (in
    /// constant time), so timing does not tell which one nearly matched.
    pub fn authenticate(&self, caller: &Caller) -> Result<Operator, ApiError> {
        if let Some(given) = caller.token.filter(|t| !t.is_empty()) {
            let mut found = None;
            for (name, token) in &self.tokens {
                if token.matches(given) && found.is_none() {
                    found = Some(name);
                }
            }
            if let Some(name) = found {
                return Ok(Operator::Token(name.clone()));
            }
        }
        if caller.operator_certificate {
            return Ok(Operator::Certificate);
        }
        if self.open_on_loopback && caller.peer.is_some_and(|p| p.ip().is_loopback()) {
            return Ok(Operator::Loopback);
        }
        Err(match caller.token.filter(|t| !t.is_empty()) {
            Some(_) => ApiError::Unauthenticated("the token is not an operator token".into()),
            None => ApiError::Unauthenticated(format!(
                "this needs an operator token (metadata or header `{TOKEN_KEY}`) or an operator's client certificate"
            )),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn roles() {
        let (c, o) = (Token::generate(), Token::generate());
        assert_ne!(c, o);
        assert_eq!(c.as_str().len(), 32);
        assert_eq!(authorize(Some(c.as_str()), &c, &o, Role::Control), Ok(Role::Control));
        assert_eq!(authorize(Some(o.as_str()), &c, &o, Role::Observe), Ok(Role::Observe));
        assert!(matches!(authorize(Some(o.as_str()), &c, &o, Role::Control), Err(ApiError::PermissionDenied(_))));
        assert!(matches!(authorize(Some("nope"), &c, &o, Role::Observe), Err(ApiError::Unauthenticated(_))));
        assert!(matches!(authorize(None, &c, &o, Role::Observe), Err(ApiError::Unauthenticated(_))));
    }

    #[test]
    fn operators_by_token_certificate_or_loopback_in_development_only() {
        let lab = "0123456789abcdef0123".to_string();
        let closed = Operators::new(vec![("lab".into(), lab.clone())], false).unwrap();
        let loopback: SocketAddr = "127.0.0.1:4000".parse().unwrap();
        let remote: SocketAddr = "192.0.2.7:4000".parse().unwrap();
        let by = |token, peer, cert| Caller { token, peer: Some(peer), operator_certificate: cert };
        assert_eq!(closed.authenticate(&by(Some(&lab), remote, false)), Ok(Operator::Token("lab".into())));
        assert_eq!(closed.authenticate(&by(None, remote, true)), Ok(Operator::Certificate));
        assert!(matches!(closed.authenticate(&by(None, loopback, false)), Err(ApiError::Unauthenticated(_))));
        assert!(matches!(closed.authenticate(&by(Some("0123456789abcdef0124"), remote, false)), Err(ApiError::Unauthenticated(m)) if m.contains("not an operator")));
        let open = Operators::new(vec![], true).unwrap();
        assert_eq!(open.authenticate(&by(None, loopback, false)), Ok(Operator::Loopback));
        assert!(open.authenticate(&by(None, remote, false)).is_err(), "development mode opens loopback only");
        assert!(Operators::new(vec![("weak".into(), "short".into())], false).unwrap_err().contains("at least 16"));
    }
}
