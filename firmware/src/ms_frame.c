/* CRC-16/MODBUS and the frame layout of docs/protocol.md ("Stream frames"). */
#include <string.h>

#include "msfw.h"

uint16_t ms_crc16(uint16_t crc, const uint8_t *data, size_t n)
{
    /* bitwise, no table: 8 shifts a byte is ~0.1 us/byte on a Cortex-M4, and no 512-byte table in flash */
    for (size_t i = 0; i < n; i++) {
        crc ^= data[i];
        for (int b = 0; b < 8; b++) {
            crc = (crc & 1u) ? (uint16_t)((crc >> 1) ^ 0xA001u) : (uint16_t)(crc >> 1);
        }
    }
    return crc;
}

size_t ms_frame(uint8_t *out, size_t cap, uint8_t type, const uint8_t *payload, uint16_t len)
{
    size_t total = 7u + (size_t)len;
    if (len > MS_MAX_PAYLOAD || total > cap) {
        return 0;
    }
    out[0] = MS_SYNC0;
    out[1] = MS_SYNC1;
    out[2] = type;
    out[3] = (uint8_t)(len & 0xFFu);
    out[4] = (uint8_t)(len >> 8);
    if (len != 0u && payload != &out[5]) {
        memmove(&out[5], payload, len);
    }
    /* the CRC covers type, length and payload, not the sync */
    uint16_t crc = ms_crc16(MS_CRC_INIT, &out[2], 3u + (size_t)len);
    out[5 + len] = (uint8_t)(crc & 0xFFu);
    out[6 + len] = (uint8_t)(crc >> 8);
    return total;
}
