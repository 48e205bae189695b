"""hcdf-trust: supply-chain and firmware integrity for robots described in HCDF."""

__version__ = "0.1.0"
