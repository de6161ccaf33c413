/* The emulated board's input: one record per sample period, sent by the simulator (`fieldlog sim --serve
 * --board emulated`) to QEMU's standard input, standing in for what the real board's ADC and timer
 * captures deliver.
 * 33 bytes, little-endian:
 *
 *   0 sync 5A A5 | 2 flags: bit0 PPS captured this period (pps_ticks valid), bit1 temperature valid
 *   | 3 i24[6] ADC counts (gyro x, y, z, accel x, y, z) | 21 u32 sample_ticks: board timer at this
 *   sample's clock edge | 25 u32 pps_ticks: board timer at the PPS edge | 29 i16 temperature, centi-deg C
 *   | 31 u16 CRC-16/CCITT-FALSE over bytes 2..30
 *
 * The sync is the frame's reversed, so an echoed frame is never taken for a record. Each record is one
 * sample: the simulator's stream is the emulated board's sample clock (firmware/README.md). */
#ifndef FW_INPUT_H
#define FW_INPUT_H

#include <stdint.h>

#include "frame.h"

#define FW_INPUT_SIZE 33
#define FW_INPUT_SYNC0 0x5Au
#define FW_INPUT_SYNC1 0xA5u
#define FW_INPUT_PPS 0x01u
#define FW_INPUT_TEMP 0x02u

typedef struct {
    int32_t counts[FW_CHANNELS];
    uint32_t sample_ticks;
    uint32_t pps_ticks;
    int16_t temp_cc;
    uint8_t flags;   /* FW_INPUT_* */
} fw_input_record;

/* Byte-at-a-time parser: sync, length, CRC; after a bad CRC it resynchronises at the next sync pair
 * inside the bytes it holds. */
typedef struct {
    uint8_t buf[FW_INPUT_SIZE];
    uint32_t len;
    uint32_t bad_crc;        /* records whose CRC failed */
    uint32_t skipped;        /* bytes discarded while looking for a sync pair */
} fw_input;

void fw_input_init(fw_input *p);

typedef enum {
    FW_INPUT_MORE = 0,     /* nothing complete yet */
    FW_INPUT_RECORD = 1,   /* a valid record, decoded into rec */
    FW_INPUT_BAD = 2,      /* a record's worth of bytes after a sync pair failed its CRC: a lost sample */
} fw_input_result;

/* Feed one byte. */
fw_input_result fw_input_feed(fw_input *p, uint8_t byte, fw_input_record *rec);

#endif
