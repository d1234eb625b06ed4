//! A bounded, lock-free channel where the newest value wins: when it is full, the sender drops
//! the oldest queued value to make room. Used wherever only the latest command matters (output
//! reports for the HID writer thread, force offsets for the servo thread).

use crossbeam_channel::{Receiver, Sender, TrySendError};

/// The sending side; cloneable, never blocks.
#[derive(Clone, Debug)]
pub struct NewestSender<T> {
    tx: Sender<T>,
    /// The sender's own handle on the queue, to evict the oldest value.
    evict: Receiver<T>,
}

/// The receiving side has gone away.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("the receiving side is gone")]
pub struct Disconnected;

/// A channel holding at most `capacity` values (at least 1).
pub fn newest_wins<T>(capacity: usize) -> (NewestSender<T>, Receiver<T>) {
    let (tx, rx) = crossbeam_channel::bounded(capacity.max(1));
    (
        NewestSender {
            tx,
            evict: rx.clone(),
        },
        rx,
    )
}

impl<T> NewestSender<T> {
    /// Queue `value`, evicting the oldest queued value if the channel is full.
    pub fn send(&self, value: T) -> Result<(), Disconnected> {
        let mut value = value;
        // Another sender may refill the slot between eviction and retry; a few rounds settle it.
        for _ in 0..8 {
            match self.tx.try_send(value) {
                Ok(()) => return Ok(()),
                Err(TrySendError::Full(back)) => {
                    value = back;
                    let _ = self.evict.try_recv();
                }
                Err(TrySendError::Disconnected(_)) => return Err(Disconnected),
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_newest_value_survives_a_full_queue() {
        let (tx, rx) = newest_wins(1);
        for v in 1..=5 {
            tx.send(v).unwrap();
        }
        assert_eq!(rx.try_recv(), Ok(5));
        assert!(rx.try_recv().is_err());
        let (tx, rx) = newest_wins(3);
        for v in 1..=10 {
            tx.send(v).unwrap();
        }
        assert_eq!(rx.try_iter().collect::<Vec<_>>(), vec![8, 9, 10]);
        drop(rx);
        // The sender's own eviction handle keeps the channel open; a dropped receiver is only
        // seen as the queue staying full, so sending still succeeds.
        assert!(tx.send(11).is_ok());
    }
}
