"""A run: what its processes share (config, option table, directory, locks) and its supervision
(the launcher, its progress view and figures, the chaos driver)."""
