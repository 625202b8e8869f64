"""The broker between API and workers: publish a batch to a shard, receive results.

``MemoryBroker`` is the embedded default: worker processes on this machine,
each fed through one pipe and answering on another. Like a stream with
consumer groups, it keeps every published batch until the worker
acknowledges it, which the worker does once a stored snapshot of the batch's
device holds it (``app.workers.coverage``); when a worker dies, a supervisor
starts a new one on fresh pipes and re-delivers every unacknowledged batch in
order. The new worker resumes its devices from their
stored snapshots, and re-delivered samples it has already used are counted
as late, not used twice.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing as mp
from collections import OrderedDict
from collections.abc import Callable
from typing import Any, Protocol

from app.core.config import Settings
from app.workers.messages import STOP, Acked, Done, Ingest, Ready, Result, decode_results, encode
from app.workers.pipes import Frames, frame, frame_all
from app.workers.process import worker_main

log = logging.getLogger(__name__)

ResultHandler = Callable[[list[Result]], None]


class Broker(Protocol):
    """What the API needs from a broker."""

    shards: int

    async def start(self, on_results: ResultHandler) -> None:
        """Start delivering; ``on_results`` is called on the event loop."""
        ...

    def publish(self, shard: int, message: Ingest) -> None:
        """Queue a batch for the shard's worker."""
        ...

    def backlog(self, shard: int) -> int:
        """Return the shard's published batches not processed yet (the overload measure)."""
        ...

    def available(self) -> bool:
        """Return whether the broker takes batches now (False while Redis is away)."""
        ...

    def healthy(self) -> bool:
        """Return whether every shard has a live consumer."""
        ...

    async def stop(self) -> None:
        """Stop workers (they snapshot their devices) and delivery."""
        ...


class _Slot:
    """One shard's worker process, the transports of its two pipes and its unacknowledged
    batches (encoded); ``processed`` are those of them it has processed (kept until a
    snapshot holds them), ``outgoing`` those published in this turn of the event loop,
    not written yet."""

    def __init__(self, shard: int) -> None:
        self.shard = shard
        self.process: Any = None
        self.inbox: asyncio.WriteTransport | None = None
        self.results: asyncio.ReadTransport | None = None
        self.read_all: asyncio.Future[None] | None = None
        self.pending: OrderedDict[str, bytes] = OrderedDict()
        self.processed: set[str] = set()
        self.outgoing: list[bytes] = []
        self.ready = asyncio.Event()


class _Results(asyncio.Protocol):
    """The API's end of a worker's results pipe: hands each frame on as it completes."""

    def __init__(self, on_frame: Callable[[bytes], None], read_all: asyncio.Future[None]) -> None:
        self._on_frame = on_frame
        self._read_all = read_all
        self._frames = Frames()

    def data_received(self, data: bytes) -> None:
        for payload in self._frames.feed(data):
            self._on_frame(payload)

    def connection_lost(self, exc: Exception | None) -> None:
        if not self._read_all.done():
            self._read_all.set_result(None)


class MemoryBroker:
    """Worker processes on this machine, supervised, with at-least-once delivery.

    Runs on the API's event loop: the pipes are read and written there, without threads
    (a queue's feeder thread and a reader thread per worker took a large share of the API
    process's time at saturation, most of it contending for the GIL).
    """

    def __init__(self, settings: Settings, shards: int) -> None:
        if shards < 1:
            raise ValueError("the memory broker needs at least one worker")
        self.settings = settings
        self.shards = shards
        self._ctx = mp.get_context("spawn")
        self._slots = [_Slot(i) for i in range(shards)]
        self._stopping = False
        self._on_results: ResultHandler = lambda _: None
        self._supervisor: asyncio.Task[None] | None = None
        self.on_restart: Callable[[int], None] = lambda _: None

    # -- lifecycle -------------------------------------------------------------------

    async def start(self, on_results: ResultHandler) -> None:
        """Start one worker per shard, wait until each is ready, then supervise them."""
        self._on_results = on_results
        for slot in self._slots:
            await self._spawn(slot)
        for slot in self._slots:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(slot.ready.wait(), timeout=120)
        self._supervisor = asyncio.create_task(self._supervise())

    async def _spawn(self, slot: _Slot) -> None:
        loop = asyncio.get_running_loop()
        slot.ready.clear()
        worker_inbox, api_inbox = self._ctx.Pipe(duplex=False)
        api_results, worker_results = self._ctx.Pipe(duplex=False)
        slot.process = self._ctx.Process(
            target=worker_main,
            args=(slot.shard, self.settings.model_dump_json(), worker_inbox, worker_results),
            name=f"locus-worker-{slot.shard}",
            daemon=True,
        )
        slot.process.start()
        # the worker holds the only other ends now: either side's exit ends the other's stream
        worker_inbox.close()
        worker_results.close()
        read_all: asyncio.Future[None] = loop.create_future()
        slot.results, _ = await loop.connect_read_pipe(
            lambda: _Results(lambda payload: self._received(slot, payload), read_all),
            api_results,
        )
        slot.read_all = read_all
        inbox, _ = await loop.connect_write_pipe(asyncio.BaseProtocol, api_inbox)
        # no await from here on: what is published meanwhile is pending, and goes once
        slot.processed.clear()
        slot.outgoing.clear()
        if slot.pending:
            inbox.write(frame_all(slot.pending.values()))
        slot.inbox = inbox

    def _received(self, slot: _Slot, payload: bytes) -> None:
        results = decode_results(payload)
        for result in results:
            if isinstance(result, Done) and result.batch_id in slot.pending:
                slot.processed.add(result.batch_id)
            elif isinstance(result, Acked):
                for batch_id in result.batch_ids:
                    slot.pending.pop(batch_id, None)
                    slot.processed.discard(batch_id)
            elif isinstance(result, Ready):
                slot.ready.set()
        self._on_results(results)

    async def _supervise(self) -> None:
        while not self._stopping:
            await asyncio.sleep(0.2)
            for slot in self._slots:
                if self._stopping or slot.process.is_alive():
                    continue
                log.warning(
                    "worker %d died (exit %s); restarting with %d pending batches",
                    slot.shard,
                    slot.process.exitcode,
                    len(slot.pending),
                )
                await self._retire(slot)
                self.on_restart(slot.shard)
                await self._spawn(slot)

    async def _retire(self, slot: _Slot) -> None:
        """Close a gone worker's pipes once what it said is read (a killed one may have left
        half a message: then after 5 s)."""
        # the transport closes itself once the worker's end is closed
        if slot.inbox is not None and not slot.inbox.is_closing():
            slot.inbox.abort()
        slot.inbox = None
        if slot.read_all is not None:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(asyncio.shield(slot.read_all), timeout=5)
        if slot.results is not None and not slot.results.is_closing():
            slot.results.close()

    async def stop(self) -> None:
        """Ask workers to snapshot and exit; wait for them and for what they said last."""
        self._stopping = True
        if self._supervisor is not None:
            self._supervisor.cancel()
        for slot in self._slots:
            if slot.inbox is not None and slot.process.is_alive():
                slot.inbox.write(frame(encode(STOP)))
        for slot in self._slots:
            if slot.process is None:
                continue
            await asyncio.to_thread(slot.process.join, 30)
            if slot.process.is_alive():
                log.warning("worker %d did not stop in time; killing it", slot.shard)
                slot.process.kill()
                await asyncio.to_thread(slot.process.join, 5)
            await self._retire(slot)

    # -- traffic ---------------------------------------------------------------------

    def publish(self, shard: int, message: Ingest) -> None:
        """Record the batch as pending and hand it to the shard's worker.

        Called on the event loop. The batches published in one turn of the loop go to
        the worker in one write, once the turn ends.
        """
        slot = self._slots[shard]
        data = encode(message)
        slot.pending[message.batch_id] = data
        slot.outgoing.append(data)
        if len(slot.outgoing) == 1:
            asyncio.get_running_loop().call_soon(self._hand_over, slot)

    def _hand_over(self, slot: _Slot) -> None:
        """Write the batches published in this turn of the loop to the worker's inbox (kept
        pending while a restarted worker's pipe is not open yet: it gets them all then)."""
        if slot.outgoing and slot.inbox is not None:
            slot.inbox.write(frame_all(slot.outgoing))
            slot.outgoing = []

    def backlog(self, shard: int) -> int:
        """Return the shard's batches not processed yet."""
        slot = self._slots[shard]
        return len(slot.pending) - len(slot.processed)

    def available(self) -> bool:
        """Return True: batches wait in this process for a worker, restarted or not."""
        return True

    def healthy(self) -> bool:
        """Return whether every worker process is alive and has said it is ready."""
        return all(
            s.process is not None and s.process.is_alive() and s.ready.is_set() for s in self._slots
        )
