//! An in-memory full-duplex byte pipe standing in for a serial line.

use std::collections::VecDeque;
use std::io::{self, Read, Write};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

#[derive(Debug, Default)]
struct PipeState {
    buf: VecDeque<u8>,
    closed: bool,
}

#[derive(Debug, Default)]
struct Pipe {
    state: Mutex<PipeState>,
    cv: Condvar,
}

impl Pipe {
    fn lock(&self) -> std::sync::MutexGuard<'_, PipeState> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }
    fn close(&self) {
        self.lock().closed = true;
        self.cv.notify_all();
    }
}

/// One end of an in-memory serial line. Reads wait up to the end's timeout, then fail with
/// `TimedOut`; once the other end is dropped or [`DuplexPort::close`]d, reads drain what is
/// left and then fail with `BrokenPipe`, and writes fail with `BrokenPipe`.
#[derive(Debug)]
pub struct DuplexPort {
    rx: Arc<Pipe>,
    tx: Arc<Pipe>,
    timeout: Duration,
}

/// Two connected ends; each read waits at most `timeout`.
pub fn duplex(timeout: Duration) -> (DuplexPort, DuplexPort) {
    let a = Arc::new(Pipe::default());
    let b = Arc::new(Pipe::default());
    (
        DuplexPort {
            rx: a.clone(),
            tx: b.clone(),
            timeout,
        },
        DuplexPort {
            rx: b,
            tx: a,
            timeout,
        },
    )
}

impl DuplexPort {
    /// Cut the line in both directions (a pulled cable).
    pub fn close(&self) {
        self.rx.close();
        self.tx.close();
    }
}

impl Drop for DuplexPort {
    fn drop(&mut self) {
        self.close();
    }
}

impl Read for DuplexPort {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if buf.is_empty() {
            return Ok(0);
        }
        let mut st = self.rx.lock();
        if st.buf.is_empty() && !st.closed {
            st = self
                .rx
                .cv
                .wait_timeout_while(st, self.timeout, |s| s.buf.is_empty() && !s.closed)
                .map(|(g, _)| g)
                .unwrap_or_else(|p| p.into_inner().0);
        }
        if st.buf.is_empty() {
            return Err(if st.closed {
                io::Error::new(io::ErrorKind::BrokenPipe, "duplex peer closed")
            } else {
                io::Error::new(io::ErrorKind::TimedOut, "no data")
            });
        }
        let n = buf.len().min(st.buf.len());
        for (o, b) in buf.iter_mut().zip(st.buf.drain(..n)) {
            *o = b;
        }
        Ok(n)
    }
}

impl Write for DuplexPort {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let mut st = self.tx.lock();
        if st.closed {
            return Err(io::Error::new(
                io::ErrorKind::BrokenPipe,
                "duplex peer closed",
            ));
        }
        st.buf.extend(buf);
        drop(st);
        self.tx.cv.notify_all();
        Ok(buf.len())
    }
    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bytes_cross_and_close_is_seen_by_the_peer() {
        let (mut a, mut b) = duplex(Duration::from_millis(20));
        a.write_all(b"hello").unwrap();
        let mut buf = [0u8; 8];
        assert_eq!(b.read(&mut buf).unwrap(), 5);
        assert_eq!(&buf[..5], b"hello");
        assert_eq!(
            b.read(&mut buf).unwrap_err().kind(),
            io::ErrorKind::TimedOut
        );
        drop(a);
        assert_eq!(
            b.read(&mut buf).unwrap_err().kind(),
            io::ErrorKind::BrokenPipe
        );
        assert_eq!(b.write(b"x").unwrap_err().kind(), io::ErrorKind::BrokenPipe);
    }
}
