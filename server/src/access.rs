//! Who may do what: bearer tokens with roles.
//!
//! Tokens come from a file (`--tokens-file`) and/or the `SPLATD_TOKENS` environment variable,
//! one per line (or separated by `;` in the variable): the roles, comma-separated, then the
//! token, e.g. `write farm-7f3a9c...` or `read,write render-node-...`. `#` starts a comment.
//!
//! | role    | may                                                                          |
//! |---------|------------------------------------------------------------------------------|
//! | `read`  | list and inspect frames, fetch images, previews, need maps and states, read `/metrics` |
//! | `write` | create-or-get a frame (`PUT`), post samples and passes, sync                  |
//! | `admin` | create and delete frames, import states (merges and pushes); implies both above |
//!
//! Each route is declared with its role in `http::router`, and guarded there by
//! `http::auth::require_role`; a route declared open has no guard.
//!
//! `/` (the live page) and `/healthz` are always open; with `--public-read` so is everything a
//! `read` token may do (for a farm's internal dashboard). Without any token configured the
//! server is open to everyone, and says so in its log at start.
//!
//! A missing or unknown token is refused as such ([`Refused`]; answered 401), a known token
//! without the role likewise (403); either way the request is not run. Tokens are compared in constant time (for tokens of equal length) and
//! never logged: the log names a token only by its position in the configuration.

use subtle::ConstantTimeEq;

/// What a request needs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// Read frames and images.
    Read,
    /// Send samples.
    Write,
    /// Create, delete, merge.
    Admin,
}

impl Role {
    fn name(self) -> &'static str {
        match self {
            Role::Read => "read",
            Role::Write => "write",
            Role::Admin => "admin",
        }
    }
}

/// One configured token.
#[derive(Clone)]
struct Token {
    secret: Vec<u8>,
    read: bool,
    write: bool,
    admin: bool,
}

impl std::fmt::Debug for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Never print the secret.
        f.debug_struct("Token")
            .field("read", &self.read)
            .field("write", &self.write)
            .field("admin", &self.admin)
            .finish_non_exhaustive()
    }
}

impl Token {
    fn may(&self, role: Role) -> bool {
        self.admin
            || match role {
                Role::Read => self.read,
                Role::Write => self.write,
                Role::Admin => false,
            }
    }
}

/// The access rules of a server.
#[derive(Debug, Clone, Default)]
pub struct Auth {
    tokens: Vec<Token>,
    public_read: bool,
}

/// A token configuration that cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("token configuration, entry {entry}: {reason}")]
pub struct AuthConfigError {
    /// 1-based entry number.
    pub entry: usize,
    /// What is wrong (never the token itself).
    pub reason: String,
}

/// Shortest token accepted: 16 characters, so that a token cannot be guessed in a lifetime.
pub const MIN_TOKEN_LEN: usize = 16;

impl Auth {
    /// No tokens: everything open.
    pub fn open() -> Auth {
        Auth::default()
    }

    /// Parses token lines (see the module docs). Entries are separated by newlines or `;`.
    pub fn parse(text: &str, public_read: bool) -> Result<Auth, AuthConfigError> {
        let mut tokens = Vec::new();
        let entries = text
            .split(['\n', ';'])
            .map(|l| l.split('#').next().unwrap_or("").trim())
            .filter(|l| !l.is_empty());
        for (i, entry) in entries.enumerate() {
            let err = |reason: String| AuthConfigError {
                entry: i + 1,
                reason,
            };
            let mut parts = entry.split_whitespace();
            let (Some(roles), Some(secret), None) = (parts.next(), parts.next(), parts.next())
            else {
                return Err(err("expected `<roles> <token>`".into()));
            };
            if secret.len() < MIN_TOKEN_LEN {
                return Err(err(format!(
                    "token is {} characters long; at least {MIN_TOKEN_LEN} are required",
                    secret.len()
                )));
            }
            let mut token = Token {
                secret: secret.as_bytes().to_vec(),
                read: false,
                write: false,
                admin: false,
            };
            for role in roles.split(',') {
                match role {
                    "read" => token.read = true,
                    "write" => token.write = true,
                    "admin" => token.admin = true,
                    other => {
                        return Err(err(format!(
                            "unknown role {other:?}; roles are read, write and admin"
                        )))
                    }
                }
            }
            tokens.push(token);
        }
        Ok(Auth {
            tokens,
            public_read,
        })
    }

    /// Whether any token is configured.
    pub fn enabled(&self) -> bool {
        !self.tokens.is_empty()
    }

    /// Number of configured tokens.
    pub fn len(&self) -> usize {
        self.tokens.len()
    }

    /// Whether no token is configured.
    pub fn is_empty(&self) -> bool {
        self.tokens.is_empty()
    }

    /// The index of the token matching `presented`, comparing against every token in constant
    /// time so the time taken does not tell which (or whether one) matched.
    fn find(&self, presented: &[u8]) -> Option<usize> {
        let mut found = None;
        for (i, t) in self.tokens.iter().enumerate() {
            if bool::from(t.secret.ct_eq(presented)) {
                found = Some(i);
            }
        }
        found
    }

    /// Decides a request to a route that needs `role`: `Ok` to run it, or the error to answer.
    /// (Open routes have no guard at all, so there is no "no role" case to decide here.)
    pub fn check(&self, role: Role, authorization: Option<&[u8]>) -> Result<(), Refused> {
        if !self.enabled() || (role == Role::Read && self.public_read) {
            return Ok(());
        }
        let presented = authorization.and_then(|v| {
            let v = std::str::from_utf8(v).ok()?;
            let (scheme, token) = v.split_once(' ')?;
            scheme
                .eq_ignore_ascii_case("bearer")
                .then(|| token.trim().as_bytes())
        });
        let Some(presented) = presented else {
            return Err(Refused::NoToken);
        };
        let Some(index) = self.find(presented) else {
            return Err(Refused::UnknownToken);
        };
        if !self.tokens[index].may(role) {
            tracing::info!(token = index + 1, role = role.name(), "token lacks a role");
            return Err(Refused::LacksRole(role.name()));
        }
        Ok(())
    }
}

/// Why a request was refused by the access rules (the HTTP layer answers 401 for the first two,
/// 403 for the last).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Refused {
    /// No bearer token was presented.
    #[error("this endpoint needs an `Authorization: Bearer <token>` header")]
    NoToken,
    /// The token is not one of this server's.
    #[error("the bearer token is not valid for this server")]
    UnknownToken,
    /// A known token without the role the request needs.
    #[error("the bearer token does not have the {0:?} role this request needs")]
    LacksRole(&'static str),
}

#[cfg(test)]
mod tests {
    use super::*;

    const W: &str = "write-token-0123456789";
    const R: &str = "read-token-0123456789";
    const A: &str = "admin-token-0123456789";

    fn auth() -> Auth {
        Auth::parse(
            &format!("# farm\nwrite {W}\nread {R} # dashboards\n;admin {A}"),
            false,
        )
        .unwrap()
    }

    fn bearer(t: &str) -> Vec<u8> {
        format!("Bearer {t}").into_bytes()
    }

    #[test]
    fn roles_are_enforced() {
        let a = auth();
        assert_eq!(a.len(), 3);
        for (token, read, write, admin) in [
            (W, false, true, false),
            (R, true, false, false),
            (A, true, true, true),
        ] {
            for (role, may) in [
                (Role::Read, read),
                (Role::Write, write),
                (Role::Admin, admin),
            ] {
                let got = a.check(role, Some(&bearer(token)));
                match (may, got) {
                    (true, Ok(())) => {}
                    (false, Err(e)) => assert!(matches!(e, Refused::LacksRole(_)), "{e}"),
                    (may, got) => panic!("{role:?} with {token}: expected {may}, got {got:?}"),
                }
            }
        }
        let e = a.check(Role::Read, None).unwrap_err();
        assert_eq!(e, Refused::NoToken);
        let e = a
            .check(Role::Read, Some(&bearer("nope-nope-nope-nope")))
            .unwrap_err();
        assert_eq!(e, Refused::UnknownToken);
        let e = a
            .check(Role::Read, Some(format!("Basic {R}").as_bytes()))
            .unwrap_err();
        assert_eq!(e, Refused::NoToken, "not a bearer token");
    }

    #[test]
    fn public_read_and_open_servers() {
        let a = Auth::parse(&format!("write {W}"), true).unwrap();
        assert!(a.check(Role::Read, None).is_ok());
        assert!(a.check(Role::Write, None).is_err());
        assert!(Auth::open().check(Role::Admin, None).is_ok());
    }

    #[test]
    fn bad_configuration_is_refused_without_echoing_tokens() {
        let e = Auth::parse("write short", false).unwrap_err();
        assert!(e.to_string().contains("at least 16"), "{e}");
        assert!(!e.to_string().contains("short"), "{e}");
        let e = Auth::parse(&format!("read\nsuper {W}"), false).unwrap_err();
        assert_eq!(e.entry, 1);
        let e = Auth::parse(&format!("super {W}"), false).unwrap_err();
        assert!(e.to_string().contains("unknown role \"super\""), "{e}");
        assert!(!format!("{:?}", auth()).contains(W));
    }
}
