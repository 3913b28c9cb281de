"""An env module that fails while importing (for the clear-error test)."""

raise RuntimeError("this env module is broken on purpose")
