"""HDF5 trajectory datasets: schema (writer/reader), streaming dataset, TBPTT datamodule, legacy import."""
