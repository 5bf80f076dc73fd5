//! Serial lines on unix through termios: a real RS-485 adapter (`/dev/ttyUSB0`) and
//! pseudo-terminals for the emulator use the same code.
//!
//! [`TtyPort::open`] puts the line in raw mode (8N1, no echo, no translation), sets the baud
//! rate and makes reads return after at most 0.1 s with whatever arrived (`VMIN = 0,
//! VTIME = 1`), which the driver treats as "nothing yet" and retries until its deadline.

use std::fs::File;
use std::io::{self, Read, Write};
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::path::{Path, PathBuf};
use std::time::Duration;

use crate::error::{Error, Result};

fn baud_const(baud: u32) -> Option<libc::speed_t> {
    Some(match baud {
        9600 => libc::B9600,
        115_200 => libc::B115200,
        921_600 => libc::B921600,
        1_000_000 => libc::B1000000,
        2_000_000 => libc::B2000000,
        3_000_000 => libc::B3000000,
        4_000_000 => libc::B4000000,
        _ => return None,
    })
}

/// Put `fd` in raw mode with the given baud rate and read timeout.
fn configure(fd: libc::c_int, baud: Option<u32>, vtime_ds: u8) -> Result<()> {
    // SAFETY: a zeroed termios is a valid out-parameter for tcgetattr, which fills it.
    let mut t: libc::termios = unsafe { std::mem::zeroed() };
    // SAFETY: `fd` is an open descriptor owned by the caller; `t` is a valid pointer.
    if unsafe { libc::tcgetattr(fd, &mut t) } != 0 {
        return Err(Error::io("tty", io::Error::last_os_error()));
    }
    // SAFETY: `t` is a valid termios obtained above.
    unsafe { libc::cfmakeraw(&mut t) };
    t.c_cflag |= libc::CLOCAL | libc::CREAD;
    t.c_cc[libc::VMIN] = 0;
    t.c_cc[libc::VTIME] = vtime_ds;
    if let Some(b) = baud {
        let speed =
            baud_const(b).ok_or_else(|| Error::Config(format!("unsupported baud rate {b}")))?;
        // SAFETY: `t` is a valid termios; speed is one of the B* constants.
        unsafe {
            libc::cfsetispeed(&mut t, speed);
            libc::cfsetospeed(&mut t, speed);
        }
    }
    // SAFETY: `fd` is open; `t` is a valid, initialised termios.
    if unsafe { libc::tcsetattr(fd, libc::TCSANOW, &t) } != 0 {
        return Err(Error::io("tty", io::Error::last_os_error()));
    }
    Ok(())
}

/// A raw serial line (or the terminal side of a PTY).
#[derive(Debug)]
pub struct TtyPort {
    file: File,
    path: PathBuf,
}

impl TtyPort {
    /// Open `path` read/write, raw, at `baud` (e.g. [`super::consts::BAUD`]).
    pub fn open(path: &Path, baud: u32) -> Result<Self> {
        use std::os::unix::fs::OpenOptionsExt;
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(libc::O_NOCTTY)
            .open(path)
            .map_err(|e| Error::io("XHand serial open", e))?;
        configure(file.as_raw_fd(), Some(baud), 1)?;
        Ok(Self {
            file,
            path: path.to_path_buf(),
        })
    }
    /// The device path.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Read for TtyPort {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        match self.file.read(buf) {
            // A PTY whose other side closed reports EIO: the line is gone.
            Err(e) if e.raw_os_error() == Some(libc::EIO) => {
                Err(io::Error::new(io::ErrorKind::BrokenPipe, e))
            }
            r => r,
        }
    }
}

impl Write for TtyPort {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        match self.file.write(buf) {
            Err(e) if e.raw_os_error() == Some(libc::EIO) => {
                Err(io::Error::new(io::ErrorKind::BrokenPipe, e))
            }
            r => r,
        }
    }
    fn flush(&mut self) -> io::Result<()> {
        self.file.flush()
    }
}

/// The controlling side of a pseudo-terminal, used by the emulator. Reads wait at most
/// `poll` for data and then report `TimedOut`.
#[derive(Debug)]
pub struct PtyMaster {
    file: File,
    // Keeps the terminal side open so the master never sees a hang-up while no client has
    // the device open.
    _slave: OwnedFd,
    slave_path: PathBuf,
    poll: Duration,
}

impl PtyMaster {
    /// Create a pseudo-terminal in raw mode. Clients open [`PtyMaster::slave_path`].
    pub fn open(poll: Duration) -> Result<Self> {
        let mut master: libc::c_int = -1;
        let mut slave: libc::c_int = -1;
        // SAFETY: out-pointers are valid; name/termp/winp may be null per openpty(3).
        let rc = unsafe {
            libc::openpty(
                &mut master,
                &mut slave,
                std::ptr::null_mut(),
                std::ptr::null(),
                std::ptr::null(),
            )
        };
        if rc != 0 {
            return Err(Error::Pty(format!(
                "openpty failed: {}",
                io::Error::last_os_error()
            )));
        }
        // SAFETY: openpty returned two fresh descriptors that nothing else owns.
        let (mfd, sfd) = unsafe { (OwnedFd::from_raw_fd(master), OwnedFd::from_raw_fd(slave)) };
        configure(sfd.as_raw_fd(), None, 1)?;
        let mut name = [0 as libc::c_char; 128];
        // SAFETY: `name` is a writable buffer of the given length; sfd is a tty.
        let rc = unsafe { libc::ttyname_r(sfd.as_raw_fd(), name.as_mut_ptr(), name.len()) };
        if rc != 0 {
            return Err(Error::Pty(format!(
                "ttyname_r failed: {}",
                io::Error::from_raw_os_error(rc)
            )));
        }
        // SAFETY: ttyname_r wrote a NUL-terminated string into `name`.
        let cname = unsafe { std::ffi::CStr::from_ptr(name.as_ptr()) };
        let slave_path = PathBuf::from(cname.to_string_lossy().into_owned());
        Ok(Self {
            file: File::from(mfd),
            _slave: sfd,
            slave_path,
            poll,
        })
    }
    /// Path clients open (e.g. `/dev/pts/3`).
    pub fn slave_path(&self) -> &Path {
        &self.slave_path
    }
}

impl Read for PtyMaster {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let mut pfd = libc::pollfd {
            fd: self.file.as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        };
        let ms = self.poll.as_millis().min(i32::MAX as u128) as libc::c_int;
        // SAFETY: `pfd` is a valid pollfd for one open descriptor.
        let rc = unsafe { libc::poll(&mut pfd, 1, ms) };
        if rc < 0 {
            return Err(io::Error::last_os_error());
        }
        if rc == 0 || pfd.revents & libc::POLLIN == 0 {
            return Err(io::Error::new(io::ErrorKind::TimedOut, "no data"));
        }
        self.file.read(buf)
    }
}

impl Write for PtyMaster {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.file.write(buf)
    }
    fn flush(&mut self) -> io::Result<()> {
        self.file.flush()
    }
}
