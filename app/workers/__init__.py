"""Filter workers: device state, shards over processes, and the broker between them and the API."""
