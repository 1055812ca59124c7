"""Testing helpers for users of torm: the pytest smoke-trial plugin (:mod:`torm.testing.plugin`)."""
