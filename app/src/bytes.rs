//! Byte-buffer helpers of the link's input and the job's read-ahead.

/// Move `buf[by..len]` to the front of `buf`, in pieces of at most `by` bytes, which do not
/// overlap: `copy_within` would bring in `memmove`, 1.5 KiB of code on the MCU.
pub(crate) fn shift_to_front(buf: &mut [u8], by: usize, len: usize) {
    let mut at = 0;
    while by > 0 && at + by < len {
        let n = by.min(len - at - by);
        let Some((front, back)) = buf.split_at_mut_checked(at + by) else {
            return;
        };
        if let (Some(dst), Some(src)) = (front.get_mut(at..at + n), back.get(..n)) {
            dst.copy_from_slice(src);
        }
        at += n;
    }
}

#[cfg(test)]
mod tests {
    use super::shift_to_front;

    #[test]
    fn shift_to_front_moves_as_copy_within_does() {
        for len in 0..40 {
            for by in 0..=len {
                let original: [u8; 48] = core::array::from_fn(|i| i as u8);
                let mut expected = original;
                expected.copy_within(by..len, 0);
                let mut got = original;
                shift_to_front(&mut got, by, len);
                assert_eq!(
                    got.get(..len - by),
                    expected.get(..len - by),
                    "len {len} by {by}"
                );
            }
        }
    }
}
