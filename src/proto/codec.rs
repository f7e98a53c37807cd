//! prost's codec with small first buffers. tonic gives every call a request decoder and a
//! response encoder of 8 KiB each from the start; prac's requests are a few hundred bytes and
//! most answers under 8 KiB, so each call held some 16 KiB it rarely used, and a client that
//! opened thousands of calls made the server hold that much for each. The buffers still grow to
//! whatever a message needs.

use tonic::codec::{BufferSettings, Codec};
use tonic_prost::{ProstDecoder, ProstEncoder};

/// The first size of each call's encode and decode buffer.
const FIRST_BUFFER: usize = 1024;

/// How much an encoder gathers before it yields to the transport (tonic's default).
const YIELD_THRESHOLD: usize = 32 * 1024;

/// tonic-prost's codec with [`FIRST_BUFFER`]-byte first buffers.
#[derive(Debug)]
pub struct LeanCodec<T, U>(std::marker::PhantomData<(T, U)>);

impl<T, U> Default for LeanCodec<T, U> {
    fn default() -> Self {
        LeanCodec(std::marker::PhantomData)
    }
}

impl<T, U> Codec for LeanCodec<T, U>
where
    T: prost::Message + Send + 'static,
    U: prost::Message + Default + Send + 'static,
{
    type Encode = T;
    type Decode = U;
    type Encoder = ProstEncoder<T>;
    type Decoder = ProstDecoder<U>;

    fn encoder(&mut self) -> Self::Encoder {
        ProstEncoder::new(BufferSettings::new(FIRST_BUFFER, YIELD_THRESHOLD))
    }

    fn decoder(&mut self) -> Self::Decoder {
        ProstDecoder::new(BufferSettings::new(FIRST_BUFFER, YIELD_THRESHOLD))
    }
}
