//! `zstd_frame`: zstd frames decoded into a buffer of a size the caller bounds, for the
//! window codec `pred-zstd` and the mesh codec. A leaf.

/// `bytes` decoded as zstd frames into a new buffer of room for `most` bytes, never
/// more (a frame that would give more is an error; one that gives fewer returns them,
/// for the caller to refuse): the buffer is not zeroed first, and the decompression
/// context is one the thread keeps.
pub(super) fn zstd_frame(bytes: &[u8], most: usize) -> std::io::Result<Vec<u8>> {
    thread_local! {
        static CONTEXT: std::cell::RefCell<Option<zstd::bulk::Decompressor<'static>>> =
            const { std::cell::RefCell::new(None) };
    }
    CONTEXT.with_borrow_mut(|context| {
        let d = match context {
            Some(d) => d,
            None => context.insert(zstd::bulk::Decompressor::new()?),
        };
        let mut out = Vec::with_capacity(most);
        // Into the buffer's capacity: `most` bytes, or more if the allocator gave more,
        // which the callers' length checks refuse.
        d.decompress_to_buffer(bytes, &mut out)?;
        Ok(out)
    })
}
