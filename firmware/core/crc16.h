/* CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0; check "123456789" -> 0x29B1).
 * The frame CRC of docs/daq-protocol.md, the input records of the emulated board and the ADS131M06's
 * output CRC (its default CCITT mode) all use it. */
#ifndef FW_CRC16_H
#define FW_CRC16_H

#include <stddef.h>
#include <stdint.h>

#define FW_CRC16_INIT 0xFFFFu

/* CRC of len bytes, continuing from crc (FW_CRC16_INIT to start). */
uint16_t fw_crc16(uint16_t crc, const uint8_t *data, size_t len);

#endif
