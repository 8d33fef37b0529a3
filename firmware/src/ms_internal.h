/* What ms_core.c shares with ms_modbus.c: the device's actions, whichever transport asked for them. */
#ifndef MS_INTERNAL_H
#define MS_INTERNAL_H

#include "msfw.h"

void ms__set_outputs(ms_device *dev, uint8_t bits, uint32_t now);
void ms__heartbeat(ms_device *dev, uint16_t counter, uint32_t now);
bool ms__set_override(ms_device *dev, uint16_t tenths); /* false: refused (out of range, or the watchdog holds) */
void ms__set_watchdog_ms(ms_device *dev, uint16_t ms, uint32_t now);
void ms__watchdog_check(ms_device *dev, uint32_t now);

#endif
