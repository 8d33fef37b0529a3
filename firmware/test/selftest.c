/* Vectors for the CRC and the frame layout, written from docs/protocol.md (not from the Python codec). */
#include <stdio.h>
#include <string.h>

#include "msfw.h"

static int failures;

static void check(int ok, const char *what)
{
    if (!ok) {
        printf("FAIL %s\n", what);
        failures++;
    } else {
        printf("ok   %s\n", what);
    }
}

int main(void)
{
    /* CRC-16/MODBUS's catalogue check value: the CRC of the ASCII digits "123456789" is 0x4B37 */
    check(ms_crc16(MS_CRC_INIT, (const uint8_t *)"123456789", 9) == 0x4B37u, "crc16(\"123456789\") == 0x4B37");
    /* the CRC runs on: two calls over halves equal one over the whole */
    check(ms_crc16(ms_crc16(MS_CRC_INIT, (const uint8_t *)"1234", 4), (const uint8_t *)"56789", 5) == 0x4B37u,
          "crc16 continues across calls");
    /* docs/protocol.md's worked example: COMMAND heartbeat, counter 0x0102 */
    static const uint8_t hb[] = {0xA5, 0x5A, 0x10, 0x03, 0x00, 0x02, 0x02, 0x01, 0x27, 0xEB};
    uint8_t payload[3] = {0x02, 0x02, 0x01};
    uint8_t out[16];
    size_t n = ms_frame(out, sizeof out, MS_T_COMMAND, payload, 3);
    check(n == sizeof hb && memcmp(out, hb, sizeof hb) == 0, "heartbeat 0x0102 frame == the doc's bytes");
    /* an empty payload: the CRC over type and length only */
    n = ms_frame(out, sizeof out, 0x10, NULL, 0);
    check(n == 7 && out[3] == 0 && out[4] == 0 &&
              (out[5] | (out[6] << 8)) == ms_crc16(MS_CRC_INIT, (const uint8_t *)"\x10\x00\x00", 3),
          "an empty payload's frame");
    /* a frame that does not fit, and a payload over 4096 bytes, are refused */
    check(ms_frame(out, 8, 0x10, payload, 3) == 0, "a frame too big for the buffer is refused");
    check(ms_frame(out, sizeof out, 0x10, payload, 4097) == 0, "a payload over 4096 bytes is refused");
    printf("%s\n", failures ? "selftest FAILED" : "selftest passed");
    return failures ? 1 : 0;
}
