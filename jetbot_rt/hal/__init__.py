"""Hardware abstraction: ``base`` (the ``Camera`` and ``Drive`` interfaces, the ``Robot`` that
holds them), ``registry`` (the backend factory) and the real backends (``gst_camera``,
``motors`` on ``i2c``). Each name has one import path: its module's."""
