"""GDR-Net-style 6D pose training (torch): configuration (``config``, standard library only), data, network,
losses, loop, ONNX export, and the ``sygrid train pose`` command. torch is imported by the modules that need it,
not here."""
