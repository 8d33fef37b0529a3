"""The TOML configuration: `models` (the schema), `load` (reading a file), `checks` (rules across sections),
`warnings` (what a valid file still does that its user should know), `errors` (how a bad file is told)."""
