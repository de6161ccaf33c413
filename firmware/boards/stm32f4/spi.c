#include "spi.h"

#include "regs.h"

void spi_init(void)
{
    SPI_CR1(SPI1_BASE) = SPI_CR1_CPHA | SPI_CR1_MSTR | SPI_CR1_BR_DIV8 | SPI_CR1_SSM | SPI_CR1_SSI;
    SPI_CR1(SPI1_BASE) |= SPI_CR1_SPE;
}

void spi_transfer(const uint8_t *tx, uint8_t *rx, size_t len)
{
    for (size_t i = 0; i < len; i++) {
        while (!(SPI_SR(SPI1_BASE) & SPI_SR_TXE))
            ;
        SPI_DR(SPI1_BASE) = tx[i];
        while (!(SPI_SR(SPI1_BASE) & SPI_SR_RXNE))
            ;
        rx[i] = (uint8_t)SPI_DR(SPI1_BASE);
    }
    while (SPI_SR(SPI1_BASE) & SPI_SR_BSY)
        ;
}
