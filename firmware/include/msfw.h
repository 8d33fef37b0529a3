/*
 * millsense reference DAQ firmware: the device side of the DAQ protocol,
 * version 2 (docs/protocol.md), in freestanding C11.
 *
 * The core (src/) does framing and CRC, the DESCRIPTOR and its repeat, the
 * sample ring and its back-pressure, every COMMAND, STATUS, CONTEXT on change,
 * the heartbeat watchdog and restarts. A board implements the hardware
 * interface below (the ms_hw_* functions) and calls three entry points:
 *
 *   ms_init(dev, cfg)   at power-up and at every restart
 *   ms_tick(dev)        once per sample-clock tick (timer interrupt or main loop)
 *   ms_poll(dev)        from the main loop, as often as it can (at least once a tick)
 *
 * ms_tick is the only producer of the ring and may run in an interrupt that
 * preempts ms_poll; everything else runs in ms_poll. No heap, no libc beyond
 * string.h (memcpy, memset, memmove); see docs/firmware.md.
 */
#ifndef MSFW_H
#define MSFW_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

/* -- compile-time sizes (a board may override them with -D) ---------------- */
#ifndef MS_MAX_CHANNELS
#define MS_MAX_CHANNELS 8u
#endif
#ifndef MS_RING_SAMPLES          /* the largest ring depth a config may ask for; a power of two */
#define MS_RING_SAMPLES 512u
#endif
#ifndef MS_CONTEXT_QUEUE         /* CONTEXT changes waiting for the link */
#define MS_CONTEXT_QUEUE 4u
#endif

/* -- the protocol's numbers (docs/protocol.md) ---------------------------- */
#define MS_PROTOCOL_VERSION 2u
#define MS_SYNC0 0xA5u
#define MS_SYNC1 0x5Au
#define MS_MAX_PAYLOAD 4096u
#define MS_MAX_SAMPLES_PER_FRAME 64u

#define MS_T_SAMPLES 0x01u
#define MS_T_DESCRIPTOR 0x02u
#define MS_T_STATUS 0x03u
#define MS_T_CONTEXT 0x04u
#define MS_T_COMMAND 0x10u

#define MS_CMD_SET_OUTPUTS 0x01u
#define MS_CMD_HEARTBEAT 0x02u
#define MS_CMD_SEND_DESCRIPTOR 0x03u
#define MS_CMD_SET_OVERRIDE 0x04u

#define MS_OUT_FEED_HOLD 0x01u
#define MS_OUT_ALARM_LAMP 0x02u
#define MS_FLAG_WATCHDOG 0x01u
#define MS_FLAG_OVERRUN 0x02u
#define MS_CAP_OVERRIDE 0x01u
#define MS_CAP_CONTEXT 0x02u
#define MS_CTX_CYCLE 0x01u
#define MS_CTX_MONITOR 0x02u
#define MS_CTX_AFC_ALLOWED 0x04u
#define MS_CTX_FEED_HELD 0x08u

#define MS_OVERRIDE_NEUTRAL 1000u /* 100.0 % */
#define MS_OVERRIDE_MAX 2000u     /* 200.0 % */
#define MS_OVERRIDE_NO_READBACK 0xFFFFu

/* channel kinds */
enum { MS_KIND_OTHER = 0, MS_KIND_VOLTAGE, MS_KIND_CURRENT, MS_KIND_SPEED, MS_KIND_ENCODER,
       MS_KIND_FEED_CURRENT, MS_KIND_FEED_RATE, MS_KIND_FORCE };

/* -- CRC and frames (src/ms_frame.c) -------------------------------------- */
/* CRC-16/MODBUS: reflected polynomial 0xA001, initial 0xFFFF; `crc` carries a running value. */
uint16_t ms_crc16(uint16_t crc, const uint8_t *data, size_t n);
#define MS_CRC_INIT 0xFFFFu
/* Writes a whole frame (sync, type, length, payload, CRC) to `out`; its length, or 0 if it does not fit. */
size_t ms_frame(uint8_t *out, size_t cap, uint8_t type, const uint8_t *payload, uint16_t len);

/* -- configuration -------------------------------------------------------- */
typedef struct {
    uint8_t kind;
    char name[8]; /* ASCII letters, digits or '_', padded with zeros */
} ms_channel;

typedef enum { MS_LINK_STREAM = 0, MS_LINK_MODBUS = 1 } ms_link;

typedef struct {
    ms_link link;                     /* the framed stream (ms_poll sends and receives), or Modbus (ms_modbus_*) */
    uint16_t sample_rate_hz;
    uint8_t channel_count;            /* 1 .. MS_MAX_CHANNELS */
    ms_channel channels[MS_MAX_CHANNELS];
    uint8_t capabilities;             /* MS_CAP_* this board has */
    uint16_t ring_samples;            /* a power of two, 2 .. MS_RING_SAMPLES */
    uint8_t samples_per_frame;        /* 1 .. 64 (10 at 1 kHz: a frame every 10 ms) */
    uint16_t watchdog_ms;             /* heartbeat watchdog period, 0 = off (match [interlock] watchdog_ms) */
    uint16_t descriptor_period_ms;    /* the DESCRIPTOR's repeat, 1000 */
    uint32_t start_index;             /* the first sample's index (0) */
    bool hold_until_heartbeat;        /* keep the feed held from power-up until the first heartbeat */
} ms_config;

/* -- what the board reads from the CNC (protocol 2) ----------------------- */
typedef struct {
    uint32_t program;
    uint32_t tool;
    uint16_t operation;
    uint8_t flags;             /* MS_CTX_*; bit 3 from the CNC's own "feed held" signal */
    uint16_t override_applied; /* the override the PLC applies, 0.1 %; MS_OVERRIDE_NO_READBACK: none */
} ms_cnc;

/* -- events the core reports to the board (for its log, LEDs, a debugger) -- */
typedef enum {
    MS_EV_RESTART = 1,       /* a = first index */
    MS_EV_OUTPUTS,           /* a = outputs written, b = cause (ms_cause) */
    MS_EV_OVERRIDE,          /* a = override written (0.1 %), b = cause */
    MS_EV_OVERRIDE_REFUSED,  /* a = value asked, b = why (ms_refusal) */
    MS_EV_HEARTBEAT,         /* a = counter, b = its time (ms) */
    MS_EV_WATCHDOG,          /* the watchdog tripped: a = last heartbeat time (ms), b = now (ms) */
    MS_EV_COMMAND,           /* a = command byte, b = argument */
    MS_EV_BAD_FRAME,         /* a = bad frames so far, b = bytes skipped so far */
    MS_EV_BAD_COMMAND,       /* a = bad commands so far, b = the command byte */
    MS_EV_OVERRUN,           /* a = samples lost now, b = samples lost so far */
    MS_EV_CONTEXT,           /* a = index from which the new context holds, b = its flags */
    MS_EV_WATCHDOG_PERIOD,   /* the host set the watchdog period (Modbus holding 101): a = ms */
} ms_event;

typedef enum { MS_CAUSE_INIT = 0, MS_CAUSE_COMMAND, MS_CAUSE_WATCHDOG, MS_CAUSE_HEARTBEAT } ms_cause;
typedef enum { MS_REFUSE_RANGE = 1, MS_REFUSE_WATCHDOG, MS_REFUSE_NO_OUTPUT } ms_refusal;

/* -- counters (never reset but by a restart) ------------------------------- */
typedef struct {
    uint32_t bad_frames;        /* bad CRC, unknown type, impossible length */
    uint32_t skipped_bytes;     /* bytes dropped while hunting for a sync */
    uint32_t bad_commands;      /* a good frame with an unknown command or a wrong length */
    uint32_t commands;          /* commands taken */
    uint32_t overrun_samples;   /* samples the ring dropped (the oldest unsent) because the link stalled */
    uint32_t overrun_events;    /* times that happened */
    uint32_t override_refused;  /* override commands refused */
    uint32_t watchdog_trips;
    uint32_t frames_sent;
} ms_counters;

/* -- the device ----------------------------------------------------------- */
#define MS_RX_MAX 72u /* a COMMAND frame is at most 5 + 64 + 2 bytes (commands have 1..3-byte payloads) */
#define MS_CMD_MAX_PAYLOAD 64u
#define MS_TX_MAX (7u + 6u + 2u * MS_MAX_SAMPLES_PER_FRAME * MS_MAX_CHANNELS)

typedef struct {
    uint32_t index;
    ms_cnc cnc;
} ms_context_entry;

typedef struct {
    ms_config cfg;
    /* the ring: ms_tick writes slot head % D then advances head; ms_poll reads from tail */
    int16_t ring[MS_RING_SAMPLES * MS_MAX_CHANNELS];
    volatile uint32_t head;   /* index the next sample gets (written by ms_tick only) */
    uint32_t tail;            /* index of the oldest sample not yet framed (ms_poll only) */
    /* outputs */
    uint8_t commanded;        /* what the last set-outputs asked for */
    uint8_t outputs;          /* what is written: commanded, plus feed hold while the watchdog holds */
    uint16_t override_cmd;    /* the override commanded (0.1 %), written to the output */
    uint16_t override_applied;/* what STATUS reports */
    uint8_t flags;            /* MS_FLAG_* */
    /* watchdog */
    bool heard;               /* any heartbeat since the restart */
    uint16_t last_heartbeat;
    uint32_t last_heartbeat_ms;
    /* CNC */
    ms_cnc cnc;               /* as last read */
    uint32_t context_index;
    ms_context_entry ctxq[MS_CONTEXT_QUEUE];
    uint8_t ctxq_len;
    /* what is due on the link */
    bool descriptor_due, context_due, status_due;
    uint32_t last_descriptor_ms;
    uint8_t tx[MS_TX_MAX];
    uint16_t tx_len, tx_off;
    uint8_t tx_type;          /* of the frame in tx */
    uint8_t rx[MS_RX_MAX];
    uint16_t rx_len;
    ms_counters n;
} ms_device;

/* entry points; ms_init returns 0, or -1 for a config the core cannot run (nothing is started then) */
int ms_init(ms_device *dev, const ms_config *cfg);
void ms_tick(ms_device *dev);
void ms_poll(ms_device *dev);
/* the link was (re)connected: drop a half-sent frame and the samples kept for the host before, send the
 * DESCRIPTOR (and CONTEXT) and a STATUS first, then the samples from now on */
void ms_link_reset(ms_device *dev);
/* whether the watchdog holds the feed now */
static inline bool ms_watchdog_tripped(const ms_device *dev) { return (dev->flags & MS_FLAG_WATCHDOG) != 0u; }

/* -- Modbus (src/ms_modbus.c): the register map of docs/protocol.md over the same device ------------
 * For cfg.link = MS_LINK_MODBUS: the board's Modbus transport hands each request to one of these, from the
 * main loop (the context of ms_poll), and sends back what they write to `out` (0 bytes: no reply). */
#define MS_MODBUS_MAX_ADU 260u
/* A PDU (function code and data) to its response PDU; the response's length. */
size_t ms_modbus_pdu(ms_device *dev, const uint8_t *req, size_t len, uint8_t *out, size_t cap);
/* Modbus TCP: one whole ADU (MBAP header + PDU); another unit id gets exception 0x0B. */
size_t ms_modbus_tcp(ms_device *dev, uint8_t unit, const uint8_t *adu, size_t len, uint8_t *out, size_t cap);
/* Modbus RTU: one frame (unit, PDU, CRC) as the board's 3.5-character silence delimits it; a bad CRC or
 * another unit id: no reply (the bus may hold other devices). */
size_t ms_modbus_rtu(ms_device *dev, uint8_t unit, const uint8_t *frame, size_t len, uint8_t *out, size_t cap);

/* -- the hardware interface: the board implements these -------------------- */
/* One sample set at the tick that is happening now: cfg.channel_count raw counts, as the ADC gives them. */
void ms_hw_read_sample(int16_t *counts);
/* The outputs: bit 0 feed hold (the permissive contact open), bit 1 alarm lamp. */
void ms_hw_write_outputs(uint8_t outputs);
/* The feed-override output, 0.1 % (0 .. 2000); 1000 is the safe state. */
void ms_hw_write_override(uint16_t tenths);
/* The CNC's context and "feed held" input, and the override it applies (or MS_OVERRIDE_NO_READBACK). */
void ms_hw_read_cnc(ms_cnc *cnc);
/* Send up to n bytes without blocking; the count taken (0: the link is full now, try later). */
size_t ms_hw_tx(const uint8_t *data, size_t n);
/* Received bytes, up to max, without blocking; the count (0: none now). */
size_t ms_hw_rx(uint8_t *data, size_t max);
/* A monotonic millisecond clock (wraps at 2^32). */
uint32_t ms_hw_millis(void);
/* What the core did (may be empty). */
void ms_hw_event(ms_event ev, uint32_t a, uint32_t b);

#endif /* MSFW_H */
