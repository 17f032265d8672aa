//! The small tokio runtime a network client of the service runs on (the PostgreSQL pool, the
//! object store), so the simulation workers (OS threads) and the HTTP handlers can both wait
//! on it without entering a runtime context twice.

use std::future::Future;

/// A client's own runtime: two threads, shut down in the background when dropped.
pub(crate) struct ClientRuntime {
    /// Always `Some` until dropped (see the `Drop`).
    runtime: Option<tokio::runtime::Runtime>,
}

impl ClientRuntime {
    /// Starts the runtime, its threads named `thread_name`.
    pub(crate) fn start(thread_name: &str) -> std::io::Result<Self> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .thread_name(thread_name)
            .build()?;
        Ok(ClientRuntime {
            runtime: Some(runtime),
        })
    }

    /// The runtime's handle.
    pub(crate) fn handle(&self) -> &tokio::runtime::Handle {
        self.runtime
            .as_ref()
            .expect("the client's runtime lives as long as its client")
            .handle()
    }

    /// Runs `future` on the runtime and waits for it, from any thread (an HTTP handler's or a
    /// simulation worker's): a channel, not `block_on`, so no runtime context is entered twice.
    pub(crate) fn run<T: Send + 'static>(
        &self,
        future: impl Future<Output = T> + Send + 'static,
    ) -> T {
        let (tx, rx) = std::sync::mpsc::sync_channel(1);
        self.handle().spawn(async move {
            let _ = tx.send(future.await);
        });
        rx.recv().expect("the client's runtime dropped a task")
    }
}

impl Drop for ClientRuntime {
    fn drop(&mut self) {
        // The last handle may go on an async thread (the HTTP state at shutdown), where a
        // runtime must not be dropped blocking.
        if let Some(runtime) = self.runtime.take() {
            runtime.shutdown_background();
        }
    }
}
