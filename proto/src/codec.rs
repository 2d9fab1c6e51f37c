//! The codec of every lcrl.v1 service and client: prost's, with one check
//! before decoding. A repeated field of messages costs a couple of bytes
//! per entry on the wire and a full struct in memory (an empty
//! `Transition` is 2 bytes and ~120 bytes decoded), so a message within the
//! decoding limit could still decode to 60 times its size. The wire is
//! scanned first, and a message holding more than
//! [`MAX_REPEATED_ENTRIES`] entries of one field is refused with
//! RESOURCE_EXHAUSTED before any of it is decoded.

use std::marker::PhantomData;

use prost::bytes::Buf;
use prost::Message;
use tonic::codec::{Codec, DecodeBuf, Decoder};
use tonic::Status;
use tonic_prost::{ProstDecoder, ProstEncoder};

/// The most entries of one repeated field a message may hold (transitions
/// of a batch, sessions of an environment call), checked on the wire
/// before decoding.
pub const MAX_REPEATED_ENTRIES: usize = 4096;

/// The start of a refusal's message, so servers can count it by reason.
pub const TOO_MANY_ENTRIES: &str = "too many entries";

/// prost's codec with the repeated-entries check on decode
/// (`proto/build.rs` makes every generated stub use it).
#[derive(Debug, Clone)]
pub struct BoundedCodec<T, U>(PhantomData<(T, U)>);

impl<T, U> Default for BoundedCodec<T, U> {
    fn default() -> Self {
        BoundedCodec(PhantomData)
    }
}

impl<T, U> Codec for BoundedCodec<T, U>
where
    T: Message + Send + 'static,
    U: Message + Default + Send + 'static,
{
    type Encode = T;
    type Decode = U;
    type Encoder = ProstEncoder<T>;
    type Decoder = BoundedDecoder<U>;

    fn encoder(&mut self) -> Self::Encoder {
        ProstEncoder::default()
    }

    fn decoder(&mut self) -> Self::Decoder {
        BoundedDecoder(ProstDecoder::default())
    }
}

/// [`ProstDecoder`] behind [`check_entries`].
#[derive(Debug)]
pub struct BoundedDecoder<U>(ProstDecoder<U>);

impl<U: Message + Default> Decoder for BoundedDecoder<U> {
    type Item = U;
    type Error = Status;

    fn decode(&mut self, buf: &mut DecodeBuf<'_>) -> Result<Option<U>, Status> {
        // tonic hands over the whole message in one contiguous chunk; if it
        // ever does not, the check is skipped rather than guessed.
        if buf.chunk().len() == buf.remaining() {
            check_entries(buf.chunk(), MAX_REPEATED_ENTRIES)?;
        }
        self.0.decode(buf)
    }

    fn buffer_settings(&self) -> tonic::codec::BufferSettings {
        self.0.buffer_settings()
    }
}

/// Refuses `message` (protobuf wire format) when one of its top-level
/// length-delimited fields occurs more than `limit` times. Malformed bytes
/// pass: prost's decoder reports them with its own error.
pub fn check_entries(message: &[u8], limit: usize) -> Result<(), Status> {
    let mut counts = std::collections::HashMap::<u64, usize>::new();
    let mut rest = message;
    while !rest.is_empty() {
        let Some(key) = varint(&mut rest) else { return Ok(()) };
        let skip = match key & 7 {
            0 => match varint(&mut rest) {
                Some(_) => 0,
                None => return Ok(()),
            },
            1 => 8,
            5 => 4,
            2 => {
                let Some(len) = varint(&mut rest) else { return Ok(()) };
                let field = key >> 3;
                let count = counts.entry(field).or_insert(0);
                *count += 1;
                if *count > limit {
                    return Err(Status::resource_exhausted(format!(
                        "{TOO_MANY_ENTRIES}: field {field} of this message repeats more than {limit} times; send at most {limit} per message \
                         (for transitions: a smaller --batch)"
                    )));
                }
                usize::try_from(len).unwrap_or(usize::MAX)
            }
            // Groups (deprecated) and invalid wire types: leave to prost.
            _ => return Ok(()),
        };
        if skip > rest.len() {
            return Ok(());
        }
        rest = &rest[skip..];
    }
    Ok(())
}

/// Reads one base-128 varint, advancing `bytes`; None when it runs past
/// the end or over ten bytes.
fn varint(bytes: &mut &[u8]) -> Option<u64> {
    let mut value = 0u64;
    for (i, &byte) in bytes.iter().enumerate().take(10) {
        value |= u64::from(byte & 0x7f) << (7 * i);
        if byte & 0x80 == 0 {
            *bytes = &bytes[i + 1..];
            return Some(value);
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::v1::{Transition, TransitionBatch};

    fn batch(transitions: usize) -> Vec<u8> {
        TransitionBatch { run_id: "r".into(), actor_id: "a".into(), sequence: 7, transitions: vec![Transition::default(); transitions], ..Default::default() }.encode_to_vec()
    }

    #[test]
    fn a_message_with_too_many_entries_is_refused_before_decoding() {
        assert!(check_entries(&batch(4), 4).is_ok());
        let refused = check_entries(&batch(5), 4).unwrap_err();
        assert_eq!(refused.code(), tonic::Code::ResourceExhausted);
        assert!(refused.message().starts_with(TOO_MANY_ENTRIES), "{}", refused.message());
        // Full transitions count the same as empty ones; scalars and
        // strings beside them do not count as entries.
        let full = Transition { state: vec![0.5; 19], next_state: vec![0.5; 19], action: vec![1.0; 6], reward: -1.0, ..Default::default() };
        let bytes = TransitionBatch { run_id: "r".into(), transitions: vec![full; 3], ..Default::default() }.encode_to_vec();
        assert!(check_entries(&bytes, 3).is_ok());
        assert!(check_entries(&bytes, 2).is_err());
    }

    #[test]
    fn malformed_bytes_are_left_to_prost() {
        for bytes in [&[0x32u8, 0xff][..], &[0xff; 11], &[0x33], &[0x32, 0x05, 0x01]] {
            assert!(check_entries(bytes, 1).is_ok());
        }
        assert!(TransitionBatch::decode(&[0x32u8, 0x05, 0x01][..]).is_err());
    }
}
