"""rflscm — radiance-field localized statistical channel models from multi-beam RSRP."""

__version__ = "0.1.0"
