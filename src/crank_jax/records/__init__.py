"""Measured records: reading them (`data`, `fields`), what their columns are and the
checks on them (`columns`, `column_checks`, `checks`), the sensors they were read
through (`sensors`), and synthetic records (`synth`)."""
