/* TI ADS131M06: 6-channel simultaneous-sampling 24-bit delta-sigma ADC on SPI1 (datasheet SBAS964).
 * CLKIN 8.192 MHz from a crystal oscillator, high-resolution mode, OSR 8192: f_data = 8.192 MHz / 2 / 8192
 * = 500 Hz on all six channels at once; /DRDY falls when a sample is ready. Gain 1 (+-1.2 V full scale; the
 * analog front end divides the sensors' +-10 V by 25/3, firmware/README.md). 24-bit words; each read is one
 * 8-word frame (status, 6 channels, CRC), its CRC-16/CCITT checked. */
#ifndef FW_ADS131M06_H
#define FW_ADS131M06_H

#include <stdint.h>

#include "frame.h"

void ads_init(void);

/* Read the sample /DRDY announced; 0, or -1 when the frame's CRC failed (counts then undefined). */
int ads_read(int32_t counts[FW_CHANNELS]);

#endif
