/* The Modbus register map's device side (docs/protocol.md, "Modbus map" and version 2's registers). */
#include <string.h>

#include "msfw.h"
#include "ms_internal.h"

enum { FC_READ_COILS = 1, FC_READ_DISCRETE = 2, FC_READ_HOLDING = 3, FC_READ_INPUT = 4, FC_WRITE_COIL = 5,
       FC_WRITE_REGISTER = 6, FC_WRITE_COILS = 15, FC_WRITE_REGISTERS = 16 };
enum { EX_FUNCTION = 0x01, EX_ADDRESS = 0x02, EX_VALUE = 0x03, EX_GATEWAY_TARGET = 0x0B };

#define IR_CHANNELS 16u
#define IR_RING 1000u
#define HR_HEARTBEAT 100u
#define HR_WATCHDOG 101u
#define HR_OVERRIDE 102u
#define MAX_REGS 125u
#define MAX_BITS 2000u

static uint16_t be16(const uint8_t *p) { return (uint16_t)((uint16_t)(p[0] << 8) | p[1]); }

static void put_be16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v >> 8);
    p[1] = (uint8_t)(v & 0xFFu);
}

static size_t exception(uint8_t fc, uint8_t code, uint8_t *out)
{
    out[0] = (uint8_t)(fc | 0x80u);
    out[1] = code;
    return 2;
}

/* Input register `a`, or false if it is outside the map. */
static bool input_register(const ms_device *dev, uint32_t a, uint16_t *v)
{
    const ms_config *cfg = &dev->cfg;
    uint32_t head = dev->head;
    uint32_t c = cfg->channel_count;
    if (a >= IR_RING) {
        uint32_t off = a - IR_RING;
        if (off >= (uint32_t)cfg->ring_samples * c) {
            return false;
        }
        *v = (uint16_t)dev->ring[off]; /* slot (k mod D), channel c: 1000 + (k mod D)·C + c */
        return true;
    }
    if (a >= IR_CHANNELS) {
        uint32_t off = a - IR_CHANNELS;
        if (off >= 5u * c) {
            return false;
        }
        uint32_t ci = 0;
        while (off >= 5u) { /* off / 5 without a division: Cortex-M0+ has none, and the core calls no libgcc */
            off -= 5u;
            ci++;
        }
        const ms_channel *ch = &cfg->channels[ci];
        uint32_t w = off;
        if (w == 0u) {
            *v = ch->kind;
        } else {
            uint32_t hi = (uint8_t)ch->name[2u * (w - 1u)], lo = (uint8_t)ch->name[2u * (w - 1u) + 1u];
            *v = (uint16_t)((hi << 8) | lo); /* two name bytes a register, the first high */
        }
        return true;
    }
    switch (a) {
    case 0: *v = MS_PROTOCOL_VERSION; break;
    case 1: *v = (uint16_t)c; break;
    case 2: *v = cfg->sample_rate_hz; break;
    case 3: *v = cfg->ring_samples; break;
    case 4: *v = (uint16_t)(head >> 16); break; /* H, high word first */
    case 5: *v = (uint16_t)(head & 0xFFFFu); break;
    case 6: *v = dev->override_applied; break;
    case 7: *v = cfg->capabilities; break;
    case 8: *v = (uint16_t)(dev->cnc.program >> 16); break;
    case 9: *v = (uint16_t)(dev->cnc.program & 0xFFFFu); break;
    case 10: *v = (uint16_t)(dev->cnc.tool >> 16); break;
    case 11: *v = (uint16_t)(dev->cnc.tool & 0xFFFFu); break;
    case 12: *v = dev->cnc.operation; break;
    case 13: *v = dev->cnc.flags; break;
    case 14: *v = (uint16_t)(dev->context_index >> 16); break;
    case 15: *v = (uint16_t)(dev->context_index & 0xFFFFu); break;
    default: return false;
    }
    return true;
}

static bool holding_register(const ms_device *dev, uint32_t a, uint16_t *v)
{
    switch (a) {
    case HR_HEARTBEAT: *v = dev->last_heartbeat; return true;
    case HR_WATCHDOG: *v = dev->cfg.watchdog_ms; return true;
    case HR_OVERRIDE: *v = dev->override_cmd; return true;
    default: return false;
    }
}

static bool bit(const ms_device *dev, uint8_t fc, uint32_t a, bool *v)
{
    if (a > 1u) {
        return false;
    }
    if (fc == FC_READ_COILS) {
        *v = ((dev->commanded >> a) & 1u) != 0u; /* what the host commands */
    } else if (a == 0u) {
        *v = (dev->outputs & MS_OUT_FEED_HOLD) != 0u; /* feed hold active: commanded or from the watchdog */
    } else {
        *v = (dev->flags & MS_FLAG_WATCHDOG) != 0u;
    }
    return true;
}

/* A register write; 0, or the exception code. */
static uint8_t write_register(ms_device *dev, uint32_t a, uint16_t v, uint32_t now)
{
    switch (a) {
    case HR_HEARTBEAT: ms__heartbeat(dev, v, now); return 0;
    case HR_WATCHDOG: ms__set_watchdog_ms(dev, v, now); return 0;
    case HR_OVERRIDE: return ms__set_override(dev, v) ? 0u : (uint8_t)EX_VALUE; /* over 2000, or the watchdog holds */
    default: return EX_ADDRESS;
    }
}

size_t ms_modbus_pdu(ms_device *dev, const uint8_t *req, size_t len, uint8_t *out, size_t cap)
{
    if (len < 1u || cap < 2u + 2u * MAX_REGS) { /* the longest answer: 125 registers */
        return 0;
    }
    uint8_t fc = req[0];
    uint32_t now = ms_hw_millis();
    ms__watchdog_check(dev, now); /* a request that comes after the deadline finds it tripped */
    if (fc == FC_READ_COILS || fc == FC_READ_DISCRETE || fc == FC_READ_HOLDING || fc == FC_READ_INPUT) {
        if (len != 5u) {
            return exception(fc, EX_VALUE, out);
        }
        uint32_t a = be16(&req[1]);
        uint32_t n = be16(&req[3]);
        bool bits = fc == FC_READ_COILS || fc == FC_READ_DISCRETE;
        if (n == 0u || n > (bits ? MAX_BITS : MAX_REGS)) {
            return exception(fc, EX_VALUE, out);
        }
        out[0] = fc;
        if (bits) {
            size_t bytes = (n + 7u) / 8u;
            memset(&out[2], 0, bytes);
            for (uint32_t i = 0; i < n; i++) {
                bool v;
                if (!bit(dev, fc, a + i, &v)) {
                    return exception(fc, EX_ADDRESS, out);
                }
                if (v) {
                    out[2u + i / 8u] |= (uint8_t)(1u << (i % 8u));
                }
            }
            out[1] = (uint8_t)bytes;
            return 2u + bytes;
        }
        for (uint32_t i = 0; i < n; i++) {
            uint16_t v;
            bool ok = fc == FC_READ_INPUT ? input_register(dev, a + i, &v) : holding_register(dev, a + i, &v);
            if (!ok) {
                return exception(fc, EX_ADDRESS, out);
            }
            put_be16(&out[2u + 2u * i], v);
        }
        out[1] = (uint8_t)(2u * n);
        return 2u + 2u * n;
    }
    if (fc == FC_WRITE_COIL || fc == FC_WRITE_REGISTER) {
        if (len != 5u) {
            return exception(fc, EX_VALUE, out);
        }
        uint32_t a = be16(&req[1]);
        uint16_t v = be16(&req[3]);
        if (fc == FC_WRITE_COIL) {
            if (a > 1u) {
                return exception(fc, EX_ADDRESS, out);
            }
            if (v != 0x0000u && v != 0xFF00u) {
                return exception(fc, EX_VALUE, out);
            }
            uint8_t mask = (uint8_t)(1u << a);
            uint8_t bits = (uint8_t)(v ? (dev->commanded | mask) : (dev->commanded & (uint8_t)~mask));
            ms__set_outputs(dev, bits, now); /* coil 0 = 0 clears the feed hold and the watchdog flag together */
        } else {
            uint8_t ex = write_register(dev, a, v, now);
            if (ex != 0u) {
                return exception(fc, ex, out);
            }
        }
        memcpy(out, req, 5); /* the echo */
        return 5;
    }
    if (fc == FC_WRITE_COILS || fc == FC_WRITE_REGISTERS) {
        if (len < 6u) {
            return exception(fc, EX_VALUE, out);
        }
        uint32_t a = be16(&req[1]);
        uint32_t n = be16(&req[3]);
        uint32_t bytes = req[5];
        bool bits = fc == FC_WRITE_COILS;
        uint32_t max = bits ? 1968u : 123u; /* the most one request can carry */
        if (n == 0u || n > max || bytes != (bits ? (n + 7u) / 8u : 2u * n) || len != 6u + bytes) {
            return exception(fc, EX_VALUE, out);
        }
        if (bits) {
            if (a + n > 2u) {
                return exception(fc, EX_ADDRESS, out);
            }
            uint8_t cmd = dev->commanded;
            for (uint32_t i = 0; i < n; i++) {
                uint8_t mask = (uint8_t)(1u << (a + i));
                bool on = (((uint32_t)req[6u + i / 8u] >> (i % 8u)) & 1u) != 0u;
                cmd = (uint8_t)(on ? (cmd | mask) : (cmd & (uint8_t)~mask));
            }
            ms__set_outputs(dev, cmd, now); /* both coils in one: one output change */
        } else {
            for (uint32_t i = 0; i < n; i++) { /* all or nothing for the address; values are checked as written */
                uint16_t dummy;
                if (!holding_register(dev, a + i, &dummy)) {
                    return exception(fc, EX_ADDRESS, out);
                }
            }
            for (uint32_t i = 0; i < n; i++) {
                uint8_t ex = write_register(dev, a + i, be16(&req[6u + 2u * i]), now);
                if (ex != 0u) {
                    return exception(fc, ex, out);
                }
            }
        }
        memcpy(out, req, 5);
        return 5;
    }
    return exception(fc, EX_FUNCTION, out);
}

size_t ms_modbus_tcp(ms_device *dev, uint8_t unit, const uint8_t *adu, size_t len, uint8_t *out, size_t cap)
{
    /* MBAP: transaction id, protocol id 0, length (unit id + PDU), unit id */
    if (len < 8u || cap < MS_MODBUS_MAX_ADU || be16(&adu[2]) != 0u || be16(&adu[4]) != len - 6u) {
        return 0;
    }
    size_t n;
    if (adu[6] != unit) {
        n = exception(adu[7], EX_GATEWAY_TARGET, &out[7]); /* not this device (a gateway's answer) */
    } else {
        n = ms_modbus_pdu(dev, &adu[7], len - 7u, &out[7], cap - 7u);
        if (n == 0u) {
            return 0;
        }
    }
    memcpy(out, adu, 4);
    put_be16(&out[4], (uint16_t)(n + 1u));
    out[6] = adu[6];
    return 7u + n;
}

size_t ms_modbus_rtu(ms_device *dev, uint8_t unit, const uint8_t *frame, size_t len, uint8_t *out, size_t cap)
{
    if (len < 4u || cap < MS_MODBUS_MAX_ADU) {
        return 0;
    }
    uint16_t crc = ms_crc16(MS_CRC_INIT, frame, len - 2u);
    if ((uint8_t)(crc & 0xFFu) != frame[len - 2u] || (uint8_t)(crc >> 8) != frame[len - 1u] || frame[0] != unit) {
        return 0; /* silence: a damaged frame, or one for another device on the bus */
    }
    size_t n = ms_modbus_pdu(dev, &frame[1], len - 3u, &out[1], cap - 3u);
    if (n == 0u) {
        return 0;
    }
    out[0] = unit;
    crc = ms_crc16(MS_CRC_INIT, out, n + 1u);
    out[n + 1u] = (uint8_t)(crc & 0xFFu); /* the RTU CRC is the same CRC-16/MODBUS, low byte first */
    out[n + 2u] = (uint8_t)(crc >> 8);
    return n + 3u;
}
