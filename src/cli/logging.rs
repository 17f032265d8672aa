//! Where the command line's logs go and how they look.

/// Logs go to stderr; `LUNGMOTION_LOG` (e.g. `debug`, `lungmotion=trace`) sets the level and
/// `LUNGMOTION_LOG_FORMAT=json` writes one JSON object per line for log collectors.
pub fn init_logging(default_level: &str) {
    let filter = tracing_subscriber::EnvFilter::try_from_env("LUNGMOTION_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_level));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    if std::env::var("LUNGMOTION_LOG_FORMAT").is_ok_and(|f| f.eq_ignore_ascii_case("json")) {
        builder.json().with_current_span(true).init();
    } else {
        builder
            .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
            .init();
    }
}
