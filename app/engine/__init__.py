"""Positioning algorithms in pure numpy: no web framework, no database.

Each module is one algorithm (or one shared data structure) and is usable and
testable on its own. Services and workers call into the engine; the engine
never imports them.
"""
