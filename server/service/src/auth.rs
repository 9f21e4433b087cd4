//! Session tokens: random, compared in constant time, never logged.

use crate::error::ApiError;

/// The gRPC metadata key (and HTTP header) that carries a token.
pub const TOKEN_KEY: &str = "cutsim-token";
/// The gRPC metadata key that names the session of a haptics stream.
pub const SESSION_KEY: &str = "cutsim-session";

/// What a token lets its holder do.
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
}
