//! A slot where the newest value wins, between one writer and one reader that never wait for each
//! other (a triple buffer: each side owns a buffer and swaps it with a shared one atomically).
//! Used wherever only the latest value matters and the reader is the servo thread or is fed by
//! it: force offsets for the servo thread, output reports for the HID writer thread.

use triple_buffer::{triple_buffer, Input, Output};

/// The writing side: [`publish`](NewestWriter::publish) never blocks and never fails.
pub struct NewestWriter<T: Send> {
    input: Input<Option<T>>,
}

/// The reading side: [`take`](NewestReader::take) never blocks.
pub struct NewestReader<T: Send> {
    output: Output<Option<T>>,
}

/// A slot that starts empty.
pub fn newest<T: Copy + Send>() -> (NewestWriter<T>, NewestReader<T>) {
    let (input, output) = triple_buffer(&None);
    (NewestWriter { input }, NewestReader { output })
}

impl<T: Copy + Send> NewestWriter<T> {
    /// Make `value` the newest; one the reader has not taken yet is replaced.
    pub fn publish(&mut self, value: T) {
        self.input.write(Some(value));
    }
}

impl<T: Copy + Send> NewestReader<T> {
    /// The value published since the last `take`, if any (each value is taken at most once).
    pub fn take(&mut self) -> Option<T> {
        if self.output.update() {
            self.output.output_buffer_mut().take()
        } else {
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_reader_sees_only_the_newest_value_and_each_once() {
        let (mut tx, mut rx) = newest();
        assert_eq!(rx.take(), None);
        for v in 1..=5 {
            tx.publish(v);
        }
        assert_eq!(rx.take(), Some(5));
        assert_eq!(rx.take(), None);
        tx.publish(6);
        assert_eq!(rx.take(), Some(6));
    }

    #[test]
    fn a_writer_on_another_thread_never_loses_its_last_value() {
        let (mut tx, mut rx) = newest::<u64>();
        let writer = std::thread::spawn(move || {
            for v in 1..=200_000u64 {
                tx.publish(v);
            }
        });
        let mut last = 0;
        while !writer.is_finished() {
            if let Some(v) = rx.take() {
                assert!(v > last, "values arrive in order, newest wins");
                last = v;
            }
        }
        writer.join().unwrap();
        if let Some(v) = rx.take() {
            last = v;
        }
        assert_eq!(last, 200_000);
    }
}
