"""The paper's experiments as data (`<name>.toml`), the runner that executes their steps
with resume (`runner`), and their reports (`report`). See `spec` for the TOML format."""
