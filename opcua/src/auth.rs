//! Who may connect and what each may do: anonymous clients with the section's role, the
//! users of the users file with theirs (user names offered and taken on the signed and
//! encrypted endpoints only: async-opcua takes a password the client did not encrypt, and
//! only there is the whole message encrypted, so a password never crosses the network in
//! clear); a read-only user's view of an output
//! has no write access, and only operators may call methods.

use crate::config::{Role, Security, User};
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use ua::crypto::SecurityPolicy;
use ua::crypto::Thumbprint;
use ua::nodes::AccessLevel;
use ua::server::authenticator::{
    AuthManager, CoreServerPermissions, Password, UserToken, user_pass_security_policy_id,
};
use ua::server::{ANONYMOUS_USER_TOKEN_ID, ServerEndpoint};
use ua::types::{
    ByteString, Error, MessageSecurityMode, NodeId, StatusCode, UAString, UserTokenPolicy,
    UserTokenType,
};

/// The users and roles of a server, and its count of refused logins.
pub(crate) struct Users {
    anonymous: Role,
    users: BTreeMap<String, User>,
    /// Logins refused (a wrong user or password, a user name on an unsigned endpoint).
    pub refused: AtomicU64,
}

impl Users {
    pub(crate) fn new(anonymous: Role, users: BTreeMap<String, User>) -> Users {
        Users {
            anonymous,
            users,
            refused: AtomicU64::new(0),
        }
    }

    /// The role of `token`'s user.
    pub(crate) fn role(&self, token: &UserToken) -> Role {
        if token.0 == ANONYMOUS_USER_TOKEN_ID {
            self.anonymous
        } else {
            self.users.get(&token.0).map_or(Role::None, |u| u.role)
        }
    }

    fn refuse(&self, why: String) -> Error {
        self.refused.fetch_add(1, Ordering::Relaxed);
        tracing::warn!("OPC UA login refused: {why}");
        Error::new(StatusCode::BadIdentityTokenRejected, why)
    }
}

/// The endpoint signs and encrypts.
fn encrypted(endpoint: &ServerEndpoint) -> bool {
    endpoint.message_security_mode() == MessageSecurityMode::SignAndEncrypt
}

/// Compares without stopping at the first difference.
fn same(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

#[async_trait::async_trait]
impl AuthManager for Users {
    async fn authenticate_anonymous_token(&self, _endpoint: &ServerEndpoint) -> Result<(), Error> {
        if self.anonymous == Role::None {
            return Err(self.refuse("anonymous sessions are not allowed".into()));
        }
        Ok(())
    }

    async fn authenticate_username_identity_token(
        &self,
        endpoint: &ServerEndpoint,
        username: &str,
        password: &Password,
    ) -> Result<UserToken, Error> {
        if !encrypted(endpoint) {
            return Err(self.refuse(format!(
                "user {username:?} on an endpoint that does not encrypt: user names are \
                 taken on signed and encrypted endpoints only"
            )));
        }
        match self.users.get(username) {
            Some(u) if same(u.password.as_bytes(), password.get().as_bytes()) => {
                Ok(UserToken(username.to_string()))
            }
            _ => Err(self.refuse(format!("user {username:?}: unknown, or a wrong password"))),
        }
    }

    async fn authenticate_x509_identity_token(
        &self,
        _endpoint: &ServerEndpoint,
        _signing_thumbprint: &Thumbprint,
    ) -> Result<UserToken, Error> {
        Err(self.refuse("X.509 user tokens are not taken (the users file names users)".into()))
    }

    async fn authenticate_issued_identity_token(
        &self,
        _endpoint: &ServerEndpoint,
        _token: &ByteString,
    ) -> Result<UserToken, Error> {
        Err(self.refuse("issued tokens are not taken".into()))
    }

    fn effective_user_access_level(
        &self,
        token: &UserToken,
        user_access_level: AccessLevel,
        _node_id: &NodeId,
    ) -> AccessLevel {
        if self.role(token) == Role::Operator {
            user_access_level
        } else {
            user_access_level - AccessLevel::CURRENT_WRITE
        }
    }

    fn is_user_executable(&self, token: &UserToken, _method_id: &NodeId) -> bool {
        self.role(token) == Role::Operator
    }

    fn user_token_policies(&self, endpoint: &ServerEndpoint) -> Vec<UserTokenPolicy> {
        let mut policies = Vec::new();
        if self.anonymous != Role::None {
            policies.push(UserTokenPolicy {
                policy_id: UAString::from("anonymous"),
                token_type: UserTokenType::Anonymous,
                issued_token_type: UAString::null(),
                issuer_endpoint_url: UAString::null(),
                security_policy_uri: UAString::null(),
            });
        }
        if encrypted(endpoint) && !self.users.is_empty() {
            policies.push(UserTokenPolicy {
                policy_id: user_pass_security_policy_id(endpoint),
                token_type: UserTokenType::UserName,
                issued_token_type: UAString::null(),
                issuer_endpoint_url: UAString::null(),
                security_policy_uri: UAString::null(),
            });
        }
        policies
    }

    fn core_permissions(&self, _token: &UserToken) -> CoreServerPermissions {
        CoreServerPermissions {
            read_diagnostics: true,
        }
    }
}

/// The endpoint of `security` at path `/`.
pub(crate) fn endpoint(security: Security) -> ServerEndpoint {
    use MessageSecurityMode::{None as Open, Sign, SignAndEncrypt};
    let (policy, mode) = match security {
        Security::None => (SecurityPolicy::None, Open),
        Security::Basic256sha256Sign => (SecurityPolicy::Basic256Sha256, Sign),
        Security::Basic256sha256SignEncrypt => (SecurityPolicy::Basic256Sha256, SignAndEncrypt),
        Security::Aes128Sha256RsaoaepSign => (SecurityPolicy::Aes128Sha256RsaOaep, Sign),
        Security::Aes128Sha256RsaoaepSignEncrypt => {
            (SecurityPolicy::Aes128Sha256RsaOaep, SignAndEncrypt)
        }
    };
    ServerEndpoint::new("/", policy, mode, &[ANONYMOUS_USER_TOKEN_ID.to_string()])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn roles() {
        let mut users = BTreeMap::new();
        users.insert(
            "op".to_string(),
            User {
                password: "secret".into(),
                role: Role::Operator,
            },
        );
        users.insert(
            "ro".to_string(),
            User {
                password: "x".into(),
                role: Role::ReadOnly,
            },
        );
        let u = Users::new(Role::ReadOnly, users);
        let rw = AccessLevel::CURRENT_READ | AccessLevel::CURRENT_WRITE;
        let id = NodeId::null();
        let level = |who: &str| {
            u.effective_user_access_level(&UserToken(who.into()), rw, &id)
                .bits()
        };
        assert_eq!(level("op"), rw.bits());
        assert_eq!(level("ro"), AccessLevel::CURRENT_READ.bits());
        assert_eq!(
            level(ANONYMOUS_USER_TOKEN_ID),
            AccessLevel::CURRENT_READ.bits()
        );
        assert_eq!(level("stranger"), AccessLevel::CURRENT_READ.bits());
        assert!(u.is_user_executable(&UserToken("op".into()), &id));
        assert!(!u.is_user_executable(&UserToken("ro".into()), &id));
        assert!(same(b"abc", b"abc"));
        assert!(!same(b"abc", b"abd"));
        assert!(!same(b"abc", b"abcd"));
    }
}
