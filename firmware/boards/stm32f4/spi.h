/* SPI1 as master, mode 1 (CPOL 0, CPHA 1: the ADS131M06's), 8-bit, MSB first, PCLK2 / 8 = 10.5 MHz, polled. */
#ifndef FW_SPI_H
#define FW_SPI_H

#include <stddef.h>
#include <stdint.h>

void spi_init(void);

/* Full-duplex transfer of len bytes (rx may equal tx). */
void spi_transfer(const uint8_t *tx, uint8_t *rx, size_t len);

#endif
