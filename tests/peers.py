"""Thin wrappers around the peer libraries used as AEDAT4 oracles."""

import numpy as np

import evtk

DV_COMPRESSION = {"none": "NONE", "lz4": "LZ4", "zstd": "ZSTD", "lz4_high": "LZ4_HIGH", "zstd_high": "ZSTD_HIGH"}


def dv_write(path, events, triggers=None, compression="lz4", chunk=1000, imu=False, frame=False):
    """Write with dv_processing.io.MonoCameraWriter, ``chunk`` events per packet."""
    import dv_processing as dv

    cfg = dv.io.MonoCameraWriter.DAVISConfig("DVXplorer_peer", tuple(events.sensor_size))
    cfg.compression = getattr(dv.CompressionType, DV_COMPRESSION[compression])
    writer = dv.io.MonoCameraWriter(str(path), cfg)
    for lo in range(0, len(events), chunk):
        store = dv.EventStore()
        sl = slice(lo, lo + chunk)
        for t, x, y, p in zip(events.t[sl], events.x[sl], events.y[sl], events.p[sl]):
            store.push_back(int(t), int(x), int(y), bool(p))
        writer.writeEvents(store)
    if triggers is not None and len(triggers):
        packet = dv.TriggerPacket()
        for t, k in zip(triggers.t, triggers.kind):
            packet.elements.append(dv.Trigger(int(t), dv.TriggerType(int(k))))
        writer.writeTriggerPacket(packet)
    if imu:
        writer.writeImu(dv.IMU(int(events.t[-1]), 25.0, 0.0, 0.0, 9.81, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    if frame:
        w, h = events.sensor_size
        writer.writeFrame(dv.Frame(int(events.t[-1]), np.zeros((h, w), np.uint8)))
    del writer


def dv_read(path):
    """(Events, Triggers) as dv_processing.io.MonoCameraRecording reads them."""
    import dv_processing as dv

    rec = dv.io.MonoCameraRecording(str(path))
    parts = []
    if rec.isEventStreamAvailable():
        while True:
            batch = rec.getNextEventBatch()
            if batch is None:
                break
            parts.append(batch.numpy())
    size = rec.getEventResolution()
    arr = np.concatenate(parts) if parts else np.zeros(0, evtk.events.STRUCTURED_LAYOUTS["dv"])
    events = evtk.Events.from_structured(arr, size)
    t, k = [], []
    if rec.isTriggerStreamAvailable():
        while True:
            batch = rec.getNextTriggerBatch()
            if batch is None:
                break
            for trig in batch:
                t.append(trig.timestamp)
                k.append(int(trig.type))
    return events, evtk.Triggers(t, k)


def aedat_read(path):
    """(structured events, structured triggers, stream table) as aedat.Decoder reads them."""
    import aedat

    decoder = aedat.Decoder(str(path))
    events, triggers = [], []
    for packet in decoder:
        if "events" in packet:
            events.append(packet["events"])
        if "triggers" in packet:
            triggers.append(packet["triggers"])
    ev = np.concatenate(events) if events else None
    tr = np.concatenate(triggers) if triggers else None
    return ev, tr, decoder.id_to_stream()


def faery_read(path):
    import faery

    return faery.events_stream_from_file(path, t0=faery.Time(microseconds=0)).to_array()


def faery_write(path, events, compression="lz4"):
    import faery

    comp = None if compression == "none" else (compression, 1)
    faery.events_stream_from_array(events.to_structured("faery"), dimensions=events.sensor_size).to_file(
        str(path), compression=comp, zero_t0=False
    )
