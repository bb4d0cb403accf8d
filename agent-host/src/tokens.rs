//! Offline token estimates of requests, labelled as estimates wherever they are reported: text
//! counts as its characters / 4, an image as 765 tokens (a 640×480 image's cost at common
//! providers). The prompt-cache estimate is the part of a request's prefix (system prompt first,
//! then the messages in order) equal to the previous request's: what a provider's prefix cache
//! could serve, when it reports no counts of its own.

use sha2::Digest as _;

use crate::llm::{Message, Part};

/// Estimated tokens of one image.
pub const IMAGE_TOKENS: u64 = 765;

fn text_tokens(chars: usize) -> u64 {
    (chars as u64).div_ceil(4)
}

#[derive(Debug, Clone, PartialEq)]
enum Piece {
    Text(String),
    /// The image's SHA-256.
    Image([u8; 32]),
}

/// Remembers the previous request to estimate what the next one shares with it.
#[derive(Debug, Default)]
pub struct PrefixEstimate {
    previous: Vec<Piece>,
}

/// One request's estimate: all its input, and the part shared with the previous request.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct Estimate {
    pub input: u64,
    pub shared_prefix: u64,
}

impl PrefixEstimate {
    /// Estimates the request `(system, messages)` and remembers it for the next one.
    pub fn next(&mut self, system: &str, messages: &[Message]) -> Estimate {
        let mut pieces = vec![Piece::Text(system.to_string())];
        for m in messages {
            // The role separates messages (and counts as "<User>", 2 tokens).
            pieces.push(Piece::Text(format!("<{:?}>", m.role)));
            for p in &m.parts {
                pieces.push(match p {
                    Part::Text(t) => Piece::Text(t.clone()),
                    Part::Png(png) => Piece::Image(sha2::Sha256::digest(png).into()),
                });
            }
        }
        let tokens = |p: &Piece| match p {
            Piece::Text(t) => text_tokens(t.chars().count()),
            Piece::Image(_) => IMAGE_TOKENS,
        };
        let input = pieces.iter().map(tokens).sum();
        let mut shared = 0;
        for (a, b) in pieces.iter().zip(&self.previous) {
            if a == b {
                shared += tokens(a);
                continue;
            }
            if let (Piece::Text(a), Piece::Text(b)) = (a, b) {
                let common = a.chars().zip(b.chars()).take_while(|(x, y)| x == y).count();
                shared += text_tokens(common).min(tokens(&Piece::Text(a.clone())));
            }
            break;
        }
        self.previous = pieces;
        Estimate { input, shared_prefix: shared }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::llm::Role;

    #[test]
    fn the_shared_prefix_ends_where_the_requests_differ() {
        let mut e = PrefixEstimate::default();
        let sys = "s".repeat(400);
        let first = vec![Message { role: Role::User, parts: vec![Part::Text("a".repeat(40)), Part::Png(vec![1, 2])] }];
        let one = e.next(&sys, &first);
        assert_eq!(one, Estimate { input: 100 + 2 + 10 + IMAGE_TOKENS, shared_prefix: 0 });
        let mut second = first.clone();
        second.push(Message::text(Role::Assistant, "b".repeat(8)));
        second.push(Message::text(Role::User, "c".repeat(8)));
        let two = e.next(&sys, &second);
        assert_eq!(two.shared_prefix, one.input, "the whole first request is a prefix of the second");
        // An older image replaced by a note: the prefix ends at that image.
        let mut third = second.clone();
        third[0].parts[1] = Part::Text("[an older image, no longer shown]".into());
        assert_eq!(e.next(&sys, &third).shared_prefix, 100 + 2 + 10);
    }
}
