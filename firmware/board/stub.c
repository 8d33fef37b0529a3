/*
 * A board stub for the Cortex-M link check (make cross): it proves the core links on its own with
 * a board that implements the hardware interface, and nothing else from a C library but string.h.
 * The ms_hw_* bodies here do nothing; a real board's are in docs/firmware.md ("A worked example").
 */
#include <string.h>

#include "msfw.h"

/* string.h, the only library the core uses: a board takes its C library's (newlib's); the stub brings its own
 * so that the link check needs no C library installed (built with -fno-tree-loop-distribute-patterns, so
 * that the loops are not turned back into calls to themselves) */
void *memcpy(void *dst, const void *src, size_t n)
{
    uint8_t *d = dst;
    const uint8_t *s = src;
    while (n--) {
        *d++ = *s++;
    }
    return dst;
}

void *memmove(void *dst, const void *src, size_t n)
{
    uint8_t *d = dst;
    const uint8_t *s = src;
    if (d < s) {
        while (n--) {
            *d++ = *s++;
        }
    } else {
        while (n--) {
            d[n] = s[n];
        }
    }
    return dst;
}

void *memset(void *dst, int c, size_t n)
{
    uint8_t *d = dst;
    while (n--) {
        *d++ = (uint8_t)c;
    }
    return dst;
}

static ms_device dev; /* no heap: the whole device is one static object (see arm-none-eabi-size's bss) */
static volatile uint32_t millis;
static uint8_t modbus_frame[MS_MODBUS_MAX_ADU], modbus_reply[MS_MODBUS_MAX_ADU];
static volatile size_t modbus_len, modbus_reply_len;

void ms_hw_read_sample(int16_t *counts) { (void)counts; }
void ms_hw_write_outputs(uint8_t outputs) { (void)outputs; }
void ms_hw_write_override(uint16_t tenths) { (void)tenths; }
void ms_hw_read_cnc(ms_cnc *cnc) { (void)cnc; }
size_t ms_hw_tx(const uint8_t *data, size_t n) { (void)data; return n; }
size_t ms_hw_rx(uint8_t *data, size_t max) { (void)data; (void)max; return 0; }
uint32_t ms_hw_millis(void) { return millis; }
void ms_hw_event(ms_event ev, uint32_t a, uint32_t b) { (void)ev; (void)a; (void)b; }

/* the sample timer's interrupt (1 kHz) and a SysTick would call these on a real board */
void SysTick_Handler(void);
void SysTick_Handler(void)
{
    millis++;
    ms_tick(&dev);
}

void Reset_Handler(void);
void Reset_Handler(void)
{
    static const ms_config cfg = {
        .sample_rate_hz = 1000, .channel_count = 7,
        .channels = {{1, "v_uv"}, {1, "v_vw"}, {2, "i_u"}, {2, "i_v"}, {2, "i_w"}, {3, "sp_rpm"}, {4, "sp_enc"}},
        .capabilities = MS_CAP_OVERRIDE | MS_CAP_CONTEXT, .ring_samples = 512, .samples_per_frame = 10,
        .watchdog_ms = 500, .descriptor_period_ms = 1000, .start_index = 0, .hold_until_heartbeat = true,
    };
    if (ms_init(&dev, &cfg) != 0) {
        for (;;) {
        }
    }
    for (;;) {
        ms_poll(&dev);
        if (modbus_len != 0u) { /* a Modbus RTU board's UART hands over one frame at a 3.5-character silence */
            modbus_reply_len = ms_modbus_rtu(&dev, 1, modbus_frame, modbus_len, modbus_reply, sizeof modbus_reply);
            modbus_len = 0;
        }
    }
}
