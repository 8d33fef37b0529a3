/* The device side of protocol version 2: ring, commands, STATUS, CONTEXT, watchdog (docs/protocol.md). */
#include <string.h>

#include "msfw.h"
#include "ms_internal.h"

/* ms_tick may run in an interrupt: the ring slot must be written before head moves on, and ms_poll
 * must read head again after copying slots. A compiler barrier is enough on a single core. */
#if defined(__GNUC__) || defined(__clang__)
#define MS_BARRIER() __asm__ volatile("" ::: "memory")
#else
#define MS_BARRIER() ((void)0)
#endif

static void put16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)(v >> 8);
}

static void put32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)((v >> 8) & 0xFFu);
    p[2] = (uint8_t)((v >> 16) & 0xFFu);
    p[3] = (uint8_t)(v >> 24);
}

static uint16_t get16(const uint8_t *p) { return (uint16_t)(p[0] | (uint16_t)(p[1] << 8)); }

static bool valid_name_char(char c)
{
    return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_';
}

static bool config_ok(const ms_config *cfg)
{
    if ((cfg->link != MS_LINK_STREAM && cfg->link != MS_LINK_MODBUS) || cfg->sample_rate_hz == 0u || cfg->channel_count == 0u || cfg->channel_count > MS_MAX_CHANNELS) {
        return false;
    }
    uint16_t d = cfg->ring_samples;
    if (d < 2u || d > MS_RING_SAMPLES || (d & (uint16_t)(d - 1u)) != 0u) {
        return false; /* a power of two: slot = index mod D stays in order across the 2^32 wrap */
    }
    if (cfg->samples_per_frame == 0u || cfg->samples_per_frame > MS_MAX_SAMPLES_PER_FRAME ||
        cfg->samples_per_frame >= d) {
        return false;
    }
    if (cfg->descriptor_period_ms == 0u) {
        return false;
    }
    for (uint8_t c = 0; c < cfg->channel_count; c++) {
        const char *name = cfg->channels[c].name;
        if (name[0] == '\0') {
            return false;
        }
        bool ended = false;
        for (int i = 0; i < 8; i++) {
            if (name[i] == '\0') {
                ended = true;
            } else if (ended || !valid_name_char(name[i])) {
                return false; /* zeros only as padding at the end */
            }
        }
    }
    return true;
}

/* -- outputs -------------------------------------------------------------- */

static uint8_t wanted_outputs(const ms_device *dev)
{
    uint8_t o = (uint8_t)(dev->commanded & (MS_OUT_FEED_HOLD | MS_OUT_ALARM_LAMP));
    if ((dev->flags & MS_FLAG_WATCHDOG) != 0u) {
        o |= MS_OUT_FEED_HOLD;
    }
    if (dev->cfg.hold_until_heartbeat && !dev->heard) {
        o |= MS_OUT_FEED_HOLD;
    }
    return o;
}

static void apply_outputs(ms_device *dev, ms_cause cause)
{
    uint8_t o = wanted_outputs(dev);
    if (o != dev->outputs) {
        dev->outputs = o;
        ms_hw_write_outputs(o); /* at once: within the poll that decided it */
        ms_hw_event(MS_EV_OUTPUTS, o, (uint32_t)cause);
        dev->status_due = true;
    }
}

static void set_override(ms_device *dev, uint16_t tenths, ms_cause cause)
{
    if (tenths != dev->override_cmd) {
        dev->override_cmd = tenths;
        ms_hw_write_override(tenths);
        ms_hw_event(MS_EV_OVERRIDE, tenths, (uint32_t)cause);
        if (dev->cnc.override_applied == MS_OVERRIDE_NO_READBACK) {
            dev->override_applied = tenths; /* nothing reads it back: what is written is what applies, now */
            dev->status_due = true;
        }
    }
}

/* -- watchdog ------------------------------------------------------------- */

void ms__watchdog_check(ms_device *dev, uint32_t now)
{
    if (dev->cfg.watchdog_ms == 0u || !dev->heard || (dev->flags & MS_FLAG_WATCHDOG) != 0u) {
        return; /* armed by the first heartbeat (docs/protocol.md "Restarts, watchdog") */
    }
    if ((uint32_t)(now - dev->last_heartbeat_ms) < dev->cfg.watchdog_ms) {
        return;
    }
    dev->flags |= MS_FLAG_WATCHDOG;
    dev->n.watchdog_trips++;
    ms_hw_event(MS_EV_WATCHDOG, dev->last_heartbeat_ms, now);
    apply_outputs(dev, MS_CAUSE_WATCHDOG);
    /* a silent host must not leave the machine at a feed it chose */
    if ((dev->cfg.capabilities & MS_CAP_OVERRIDE) != 0u) {
        set_override(dev, MS_OVERRIDE_NEUTRAL, MS_CAUSE_WATCHDOG);
    }
    dev->status_due = true;
}

/* -- commands ------------------------------------------------------------- */

static void bad_command(ms_device *dev, uint8_t cmd)
{
    dev->n.bad_commands++;
    ms_hw_event(MS_EV_BAD_COMMAND, dev->n.bad_commands, cmd);
}

static void refuse_override(ms_device *dev, uint16_t value, ms_refusal why)
{
    dev->n.override_refused++;
    ms_hw_event(MS_EV_OVERRIDE_REFUSED, value, (uint32_t)why);
}

void ms__set_outputs(ms_device *dev, uint8_t bits, uint32_t now)
{
    dev->commanded = (uint8_t)(bits & (MS_OUT_FEED_HOLD | MS_OUT_ALARM_LAMP));
    if ((dev->commanded & MS_OUT_FEED_HOLD) == 0u) {
        /* the host's clear: releases a watchdog hold, which re-arms from the last heartbeat heard
         * (at once if that is more than a period ago: watchdog_check below) */
        dev->flags &= (uint8_t)~MS_FLAG_WATCHDOG;
    }
    apply_outputs(dev, MS_CAUSE_COMMAND);
    ms__watchdog_check(dev, now);
}

void ms__heartbeat(ms_device *dev, uint16_t counter, uint32_t now)
{
    if (dev->heard && counter == dev->last_heartbeat) {
        return; /* only a changed counter proves a live host */
    }
    dev->heard = true;
    dev->last_heartbeat = counter;
    dev->last_heartbeat_ms = now;
    ms_hw_event(MS_EV_HEARTBEAT, counter, now);
    apply_outputs(dev, MS_CAUSE_HEARTBEAT); /* hold_until_heartbeat: released by the first one */
}

bool ms__set_override(ms_device *dev, uint16_t tenths)
{
    if ((dev->cfg.capabilities & MS_CAP_OVERRIDE) == 0u) {
        refuse_override(dev, tenths, MS_REFUSE_NO_OUTPUT);
    } else if (tenths > MS_OVERRIDE_MAX) {
        refuse_override(dev, tenths, MS_REFUSE_RANGE); /* the device bounds it too, whatever the host sends */
    } else if ((dev->flags & MS_FLAG_WATCHDOG) != 0u && tenths > MS_OVERRIDE_NEUTRAL) {
        refuse_override(dev, tenths, MS_REFUSE_WATCHDOG); /* tripped: slower only, until the host's clear */
    } else {
        set_override(dev, tenths, MS_CAUSE_COMMAND);
        return true;
    }
    return false;
}

void ms__set_watchdog_ms(ms_device *dev, uint16_t ms, uint32_t now)
{
    if (ms != dev->cfg.watchdog_ms) {
        dev->cfg.watchdog_ms = ms;
        ms_hw_event(MS_EV_WATCHDOG_PERIOD, ms, 0);
        if (dev->heard) {
            dev->last_heartbeat_ms = now; /* a new period counts from now, not from a heartbeat it never judged */
        }
    }
}

static void on_command(ms_device *dev, const uint8_t *p, uint16_t len, uint32_t now)
{
    uint8_t cmd = p[0];
    uint16_t arg = 0;
    dev->status_due = true; /* a STATUS after every command, a refused one too */
    switch (cmd) {
    case MS_CMD_SET_OUTPUTS:
        if (len != 2u) {
            bad_command(dev, cmd);
            return;
        }
        arg = (uint16_t)(p[1] & (MS_OUT_FEED_HOLD | MS_OUT_ALARM_LAMP));
        ms_hw_event(MS_EV_COMMAND, cmd, arg);
        ms__set_outputs(dev, (uint8_t)arg, now);
        break;
    case MS_CMD_HEARTBEAT:
        if (len != 3u) {
            bad_command(dev, cmd);
            return;
        }
        arg = get16(&p[1]);
        ms_hw_event(MS_EV_COMMAND, cmd, arg);
        ms__heartbeat(dev, arg, now);
        break;
    case MS_CMD_SEND_DESCRIPTOR:
        if (len != 1u) {
            bad_command(dev, cmd);
            return;
        }
        ms_hw_event(MS_EV_COMMAND, cmd, 0);
        dev->descriptor_due = true;
        break;
    case MS_CMD_SET_OVERRIDE:
        if (len != 3u) {
            bad_command(dev, cmd);
            return;
        }
        arg = get16(&p[1]);
        ms_hw_event(MS_EV_COMMAND, cmd, arg);
        (void)ms__set_override(dev, arg);
        break;
    default:
        bad_command(dev, cmd);
        return;
    }
    dev->n.commands++;
}

/* -- receiving: hunt for a sync, never trust a length before the CRC agrees ---- */

static void bad_frame(ms_device *dev)
{
    dev->n.bad_frames++;
    dev->n.skipped_bytes++; /* the sync byte dropped; the hunt goes on from the next byte */
    ms_hw_event(MS_EV_BAD_FRAME, dev->n.bad_frames, dev->n.skipped_bytes);
}

static bool rx_parse(ms_device *dev, uint32_t now)
{
    size_t i = 0;
    bool progress = false;
    while (i < dev->rx_len) {
        const uint8_t *f = &dev->rx[i];
        size_t avail = dev->rx_len - i;
        if (f[0] != MS_SYNC0) {
            dev->n.skipped_bytes++;
            i++;
            continue;
        }
        if (avail < 2u) {
            break;
        }
        if (f[1] != MS_SYNC1) {
            dev->n.skipped_bytes++;
            i++;
            continue;
        }
        if (avail < 5u) {
            break;
        }
        uint16_t len = get16(&f[3]);
        if (f[2] != MS_T_COMMAND || len == 0u || len > MS_CMD_MAX_PAYLOAD) {
            bad_frame(dev); /* a type a device never takes, or an impossible length */
            i++;
            continue;
        }
        if (avail < 7u + (size_t)len) {
            break;
        }
        if (ms_crc16(MS_CRC_INIT, &f[2], 3u + (size_t)len) != get16(&f[5 + len])) {
            bad_frame(dev);
            i++;
            continue;
        }
        on_command(dev, &f[5], len, now);
        i += 7u + (size_t)len;
    }
    if (i > 0u) {
        progress = true;
        memmove(dev->rx, &dev->rx[i], dev->rx_len - i);
        dev->rx_len = (uint16_t)(dev->rx_len - i);
    }
    return progress;
}

static void receive(ms_device *dev, uint32_t now)
{
    /* bounded: a flood of bytes cannot stop the samples from going out */
    for (int round = 0; round < 8; round++) {
        size_t got = 0;
        if (dev->rx_len < MS_RX_MAX) {
            got = ms_hw_rx(&dev->rx[dev->rx_len], MS_RX_MAX - dev->rx_len);
            dev->rx_len = (uint16_t)(dev->rx_len + got);
        }
        bool progress = rx_parse(dev, now);
        if (got == 0u && !progress) {
            break;
        }
    }
}

/* -- the CNC's inputs ------------------------------------------------------ */

static bool same_context(const ms_cnc *a, const ms_cnc *b)
{
    return a->program == b->program && a->tool == b->tool && a->operation == b->operation && a->flags == b->flags;
}

static void read_cnc(ms_device *dev)
{
    ms_cnc c;
    memset(&c, 0, sizeof c);
    c.override_applied = MS_OVERRIDE_NO_READBACK;
    ms_hw_read_cnc(&c);
    c.flags &= (uint8_t)(MS_CTX_CYCLE | MS_CTX_MONITOR | MS_CTX_AFC_ALLOWED | MS_CTX_FEED_HELD);
    if ((dev->cfg.capabilities & MS_CAP_CONTEXT) != 0u && !same_context(&c, &dev->cnc)) {
        dev->context_index = dev->head; /* seen between samples head-1 and head: holds from head */
        ms_context_entry *e = (dev->ctxq_len < MS_CONTEXT_QUEUE) ? &dev->ctxq[dev->ctxq_len++]
                                                                : &dev->ctxq[MS_CONTEXT_QUEUE - 1u];
        e->index = dev->context_index;
        e->cnc = c; /* a full queue (a stalled link) keeps the newest change in its last place */
        ms_hw_event(MS_EV_CONTEXT, dev->context_index, c.flags);
    }
    dev->cnc = c;
    uint16_t applied = (c.override_applied == MS_OVERRIDE_NO_READBACK) ? dev->override_cmd : c.override_applied;
    if (applied != dev->override_applied) {
        dev->override_applied = applied;
        dev->status_due = true; /* the host learns of the applied override as it moves */
    }
}

/* -- the ring --------------------------------------------------------------- */

/* The ring keeps the newest D-1 samples; when the link stalls longer, the oldest unsent ones are
 * overwritten. They are counted here and flagged in the next STATUS, and the index gap tells the host. */
static void ring_check(ms_device *dev)
{
    uint32_t h = dev->head;
    uint32_t behind = h - dev->tail;
    uint32_t keep = (uint32_t)dev->cfg.ring_samples - 1u;
    if (behind > keep) {
        uint32_t lost = behind - keep;
        dev->tail += lost;
        dev->n.overrun_samples += lost;
        dev->n.overrun_events++;
        dev->flags |= MS_FLAG_OVERRUN;
        dev->status_due = true;
        ms_hw_event(MS_EV_OVERRUN, lost, dev->n.overrun_samples);
    }
}

/* -- sending ---------------------------------------------------------------- */

static void frame_tx(ms_device *dev, uint8_t type, uint16_t len)
{
    dev->tx_len = (uint16_t)ms_frame(dev->tx, sizeof dev->tx, type, &dev->tx[5], len);
    dev->tx_off = 0;
    dev->tx_type = type;
}

static void build_descriptor(ms_device *dev)
{
    uint8_t *p = &dev->tx[5];
    const ms_config *cfg = &dev->cfg;
    p[0] = MS_PROTOCOL_VERSION;
    put16(&p[1], cfg->sample_rate_hz);
    p[3] = cfg->channel_count;
    size_t o = 4;
    for (uint8_t c = 0; c < cfg->channel_count; c++) {
        p[o++] = cfg->channels[c].kind;
        for (int i = 0; i < 8; i++) {
            p[o++] = (uint8_t)cfg->channels[c].name[i];
        }
    }
    p[o++] = cfg->capabilities;
    frame_tx(dev, MS_T_DESCRIPTOR, (uint16_t)o);
}

static void build_context(ms_device *dev, const ms_context_entry *e)
{
    uint8_t *p = &dev->tx[5];
    put32(&p[0], e->index);
    put32(&p[4], e->cnc.program);
    put32(&p[8], e->cnc.tool);
    put16(&p[12], e->cnc.operation);
    p[14] = e->cnc.flags;
    frame_tx(dev, MS_T_CONTEXT, 15u);
}

static void build_status(ms_device *dev)
{
    uint8_t *p = &dev->tx[5];
    p[0] = dev->outputs;
    p[1] = dev->flags;
    put16(&p[2], dev->last_heartbeat);
    put16(&p[4], dev->override_applied);
    dev->flags &= (uint8_t)~MS_FLAG_OVERRUN; /* reported: an overrun since the last STATUS */
    frame_tx(dev, MS_T_STATUS, 6u);
}

static bool build_samples(ms_device *dev)
{
    const uint32_t mask = (uint32_t)dev->cfg.ring_samples - 1u;
    const uint8_t c_count = dev->cfg.channel_count;
    const uint8_t s_count = dev->cfg.samples_per_frame;
    for (int attempt = 0; attempt < 4; attempt++) {
        ring_check(dev);
        uint32_t first = dev->tail;
        if ((uint32_t)(dev->head - first) < s_count) {
            return false; /* whole frames only, as a DAQ with its own sample clock sends them */
        }
        uint8_t *p = &dev->tx[5];
        put32(&p[0], first);
        p[4] = c_count;
        p[5] = s_count;
        size_t o = 6;
        for (uint8_t s = 0; s < s_count; s++) {
            const int16_t *slot = &dev->ring[(size_t)((first + s) & mask) * c_count];
            for (uint8_t c = 0; c < c_count; c++) {
                put16(&p[o], (uint16_t)slot[c]);
                o += 2u;
            }
        }
        MS_BARRIER();
        if ((uint32_t)(dev->head - first) > mask) {
            continue; /* ms_tick overwrote the oldest while they were copied: ring_check drops them */
        }
        dev->tail = first + s_count;
        frame_tx(dev, MS_T_SAMPLES, (uint16_t)o);
        return true;
    }
    return false;
}

static bool build_next(ms_device *dev, uint32_t now)
{
    if (dev->descriptor_due) {
        dev->descriptor_due = false;
        dev->last_descriptor_ms = now;
        if ((dev->cfg.capabilities & MS_CAP_CONTEXT) != 0u) {
            dev->context_due = true; /* the CONTEXT goes with every DESCRIPTOR: once a second too */
        }
        build_descriptor(dev);
        return true;
    }
    if (dev->ctxq_len > 0u) {
        ms_context_entry e = dev->ctxq[0];
        dev->ctxq_len--;
        memmove(&dev->ctxq[0], &dev->ctxq[1], (size_t)dev->ctxq_len * sizeof dev->ctxq[0]);
        build_context(dev, &e);
        return true;
    }
    if (dev->context_due) {
        ms_context_entry e;
        dev->context_due = false;
        e.index = dev->context_index;
        e.cnc = dev->cnc;
        build_context(dev, &e);
        return true;
    }
    if (dev->status_due) {
        dev->status_due = false;
        build_status(dev);
        return true;
    }
    return build_samples(dev);
}

static void pump(ms_device *dev, uint32_t now)
{
    for (int guard = 0; guard < 64; guard++) {
        if (dev->tx_off < dev->tx_len) {
            size_t n = ms_hw_tx(&dev->tx[dev->tx_off], (size_t)(dev->tx_len - dev->tx_off));
            dev->tx_off = (uint16_t)(dev->tx_off + n);
            if (dev->tx_off < dev->tx_len) {
                return; /* the link is full: what is left goes next poll */
            }
            dev->n.frames_sent++;
        }
        dev->tx_len = 0;
        dev->tx_off = 0;
        if (!build_next(dev, now)) {
            return;
        }
    }
}

/* -- entry points ------------------------------------------------------------ */

int ms_init(ms_device *dev, const ms_config *cfg)
{
    if (!config_ok(cfg)) {
        return -1;
    }
    memset(dev, 0, sizeof *dev);
    dev->cfg = *cfg;
    dev->head = cfg->start_index;
    dev->tail = cfg->start_index;
    uint32_t now = ms_hw_millis();
    /* a restart: outputs to their safe state, whatever they were before it */
    dev->commanded = 0;
    dev->outputs = wanted_outputs(dev);
    ms_hw_write_outputs(dev->outputs);
    dev->override_cmd = MS_OVERRIDE_NEUTRAL;
    dev->override_applied = MS_OVERRIDE_NEUTRAL;
    if ((cfg->capabilities & MS_CAP_OVERRIDE) != 0u) {
        ms_hw_write_override(MS_OVERRIDE_NEUTRAL);
    }
    ms_hw_event(MS_EV_RESTART, dev->head, 0);
    ms_hw_event(MS_EV_OUTPUTS, dev->outputs, MS_CAUSE_INIT);
    if ((cfg->capabilities & MS_CAP_OVERRIDE) != 0u) {
        ms_hw_event(MS_EV_OVERRIDE, MS_OVERRIDE_NEUTRAL, MS_CAUSE_INIT);
    }
    memset(&dev->cnc, 0, sizeof dev->cnc);
    dev->cnc.override_applied = MS_OVERRIDE_NO_READBACK;
    ms_hw_read_cnc(&dev->cnc);
    dev->context_index = dev->head;
    dev->descriptor_due = true; /* a board that restarts sends a DESCRIPTOR first */
    dev->status_due = true;
    dev->last_descriptor_ms = now;
    return 0;
}

void ms_tick(ms_device *dev)
{
    uint32_t k = dev->head;
    int16_t *slot = &dev->ring[(size_t)(k & ((uint32_t)dev->cfg.ring_samples - 1u)) * dev->cfg.channel_count];
    ms_hw_read_sample(slot);
    MS_BARRIER();
    dev->head = k + 1u;
}

void ms_link_reset(ms_device *dev)
{
    /* a new host gets the stream from its connection on, as from a serial line: not the backlog the ring held
     * for a host that is gone (a burst of old samples would look to it like a DAQ running fast) */
    dev->tail = dev->head;
    dev->tx_len = 0;
    dev->tx_off = 0;
    dev->rx_len = 0;
    dev->descriptor_due = true;
    dev->status_due = true;
}

void ms_poll(ms_device *dev)
{
    uint32_t now = ms_hw_millis();
    ms__watchdog_check(dev, now); /* first: a heartbeat that comes after the deadline finds it tripped */
    if (dev->cfg.link == MS_LINK_MODBUS) {
        read_cnc(dev); /* the host reads the registers (ms_modbus.c): no frames, no stream to pump */
        return;
    }
    receive(dev, now);
    read_cnc(dev);
    ring_check(dev);
    if ((uint32_t)(now - dev->last_descriptor_ms) >= dev->cfg.descriptor_period_ms) {
        dev->descriptor_due = true;
    }
    pump(dev, now);
}
