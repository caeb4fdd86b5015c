//! The background thread each server runs on, with its own tokio runtime.

use std::io;
use std::net::{Ipv4Addr, SocketAddr, TcpListener as StdTcpListener};
use std::thread::JoinHandle;
use std::time::Duration;

use tokio::net::{TcpListener, TcpStream};
use tokio::sync::oneshot;

pub(crate) const SHUTDOWN_GRACE: Duration = Duration::from_secs(2);

/// A listener served on its own thread and tokio runtime until dropped.
pub(crate) struct Background {
    pub(crate) addr: SocketAddr,
    pub(crate) stop: Option<oneshot::Sender<()>>,
    pub(crate) thread: Option<JoinHandle<()>>,
}

impl Background {
    /// Binds `127.0.0.1:0` and serves each accepted connection with `serve` (called
    /// inside the runtime, where it may spawn tasks) until the value is dropped.
    pub(crate) fn start<F>(name: &str, mut serve: F) -> io::Result<Self>
    where
        F: FnMut(TcpStream) + Send + 'static,
    {
        let listener = StdTcpListener::bind((Ipv4Addr::LOCALHOST, 0))?;
        listener.set_nonblocking(true)?;
        let addr = listener.local_addr()?;
        // One thread: on a small machine that also runs the client under test, a
        // work-stealing runtime's cross-thread wake-ups cost the client CPU.
        let runtime = tokio::runtime::Builder::new_current_thread()
            .thread_name(format!("{name}-blocking"))
            .enable_all()
            .build()?;
        let (stop, mut stopped) = oneshot::channel::<()>();
        let thread = std::thread::Builder::new()
            .name(name.to_owned())
            .spawn(move || {
                runtime.block_on(async move {
                    let listener = match TcpListener::from_std(listener) {
                        Ok(listener) => listener,
                        Err(err) => {
                            eprintln!("arkit-s3-testbed: {err}");
                            return;
                        }
                    };
                    loop {
                        tokio::select! {
                            accepted = listener.accept() => match accepted {
                                Ok((socket, _)) => {
                                    let _ = socket.set_nodelay(true);
                                    serve(socket);
                                }
                                // Out of descriptors and the like: wait, then go on.
                                Err(_) => tokio::time::sleep(Duration::from_millis(10)).await,
                            },
                            _ = &mut stopped => break,
                        }
                    }
                    // The listener drops here: the port is free before the drop returns.
                });
                // Drops every connection task (closing its socket).
                runtime.shutdown_timeout(SHUTDOWN_GRACE);
            })?;
        Ok(Self {
            addr,
            stop: Some(stop),
            thread: Some(thread),
        })
    }
}

impl Drop for Background {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}
