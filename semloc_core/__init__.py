"""semloc core: the algorithms, pure (arrays in, arrays out; no bus, no logging, no global state)."""
