/* The real board's clocks and pins (STM32F405RG / STM32F407VG, 8 MHz crystal): firmware/README.md has the
 * wiring. */
#ifndef FW_BOARD_H
#define FW_BOARD_H

#include "regs.h"

#define HSE_HZ 8000000u
#define CORE_HZ 168000000u     /* SYSCLK = HCLK: PLL from the HSE */
#define PCLK1_HZ 42000000u     /* APB1; its timers (TIM2) run at 2 x PCLK1 = 84 MHz */
#define PCLK2_HZ 84000000u     /* APB2 (USART1, SPI1, ADC1) */
#define DAQ_BAUD 921600u       /* the frames, USART1 */

/* Pins: port base and number */
#define PIN_PPS GPIOA_BASE, 0u        /* TIM2_CH1 (AF1): GPS 1PPS, via the level shifter */
#define PIN_DRDY GPIOA_BASE, 1u       /* TIM2_CH2 (AF1) and EXTI1: ADS131M06 /DRDY */
#define PIN_ADC_RESET GPIOA_BASE, 3u  /* ADS131M06 /SYNC/RESET */
#define PIN_ADC_CS GPIOA_BASE, 4u     /* ADS131M06 /CS */
#define PIN_SCK GPIOA_BASE, 5u        /* SPI1 (AF5) */
#define PIN_MISO GPIOA_BASE, 6u
#define PIN_MOSI GPIOA_BASE, 7u
#define PIN_DAQ_TX GPIOB_BASE, 6u     /* USART1_TX (AF7): to the USB-serial adapter's RX */

#endif
