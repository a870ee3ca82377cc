"""A plugin whose import fails, as a broken installation would."""
import splatzoo_missing_dependency  # noqa: F401

SPEC = None
