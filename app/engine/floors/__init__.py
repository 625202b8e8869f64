"""Floor selection: which floor a device is on, window by window.

Two selectors share one interface (``selection.FloorSelector``); the
configuration names one (``FloorParams.method``, ``selection.floor_selector_class``):

- ``forward``: the engine's default, a forward filter over floors (a hidden
  Markov model whose state is the floor) on the evidence of ``evidence``;
- ``patent``: the floor selection of Eurasian patent 047000, the
  E_L ranking, with hysteresis added.

Both read a barometer's climb (``pressure``), take one ``window.FloorWindow``
per positioning window and return the active floors (those heard within
``history_ms``) with the chosen floor first; without any, no floor. Their
constants are in ``params``. Import from the modules; the package exports
nothing.
"""
