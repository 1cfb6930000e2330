"""The paper's experiments as data (`<name>.toml`), the runner that executes their steps
with resume (`runner`; `schedule` takes the steps, `steps` holds what each verb does), and
their reports (`report`). See `spec` for the TOML format."""
